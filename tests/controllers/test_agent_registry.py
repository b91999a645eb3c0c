"""The agent registry (``controllers.agents.registry``): one record per agent, read by the
command lines, the evaluation, the report and the plots."""

from __future__ import annotations

import pytest

from controllers.agents.registry import AGENT_REGISTRY, AgentSpec, agent_spec, make_agent
from lfm_env.config import ConfigError

# The figures' colours and the tables' order of the agents, as the reports have drawn them
# (the rl agent's colour is the one its name used to get from the fallback colours).
COLOURS = {
    "nominal": "tab:gray",
    "pf": "tab:orange",
    "scenario": "tab:blue",
    "scenario_particles": "tab:green",
    "robust": "tab:red",
    "oracle": "tab:purple",
    "rl": "tab:olive",
    "dompc": "tab:brown",
}


def test_each_record_names_its_class_and_the_registry_is_in_table_order():
    assert {n: s.colour for n, s in AGENT_REGISTRY.items()} == COLOURS  # in this order
    orders = [s.order for s in AGENT_REGISTRY.values()]
    assert orders == sorted(orders) and len(set(orders)) == len(orders)
    for name, spec in AGENT_REGISTRY.items():
        assert isinstance(spec, AgentSpec) and spec.name == name == spec.agent_class.name
        assert spec.label and spec.short_label and "\n" not in spec.label + spec.short_label
    assert len({s.colour for s in AGENT_REGISTRY.values()}) == len(AGENT_REGISTRY)


def test_the_registry_is_read_only():
    with pytest.raises(TypeError):
        AGENT_REGISTRY["mine"] = AGENT_REGISTRY["nominal"]  # type: ignore[index]


def test_only_the_agent_that_reads_the_truth_gets_the_env():
    assert [n for n, s in AGENT_REGISTRY.items() if s.reads_truth] == ["oracle"]
    with pytest.raises(ValueError, match="only the oracle reads the truth"):
        make_agent("nominal", env=object())
    with pytest.raises(ValueError, match="needs env="):
        make_agent("oracle")


def test_unknown_names_list_the_registered_agents():
    with pytest.raises(ValueError, match=r"unknown agent 'nope'; choose one of \['nominal'"):
        agent_spec("nope")
    with pytest.raises(ValueError, match="unknown agent 'nope'"):
        make_agent("nope")


def test_a_records_own_check_runs_before_the_agent_is_built():
    with pytest.raises(ConfigError, match="agents.rl_policy"):
        make_agent("rl", {"agents": {"rl_policy": None}})
