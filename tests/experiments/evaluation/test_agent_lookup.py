"""Evaluating a user's agents (``controllers.agents.registry``: one record for every agent):
factories, agent objects, 'module:attribute' and registered ones, how they are named,
checked and sent to workers, and how the evaluation runs them."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from controllers.agents.protocol import Agent
from controllers.agents.registry import (
    AGENT_REGISTRY,
    AgentSpec,
    AgentSpecError,
    register_agent,
    resolve_agent,
)
from controllers.config import ExperimentConfig
from experiments.evaluation import run as evaluation
from experiments.evaluation.run import (
    agent_seed,
    evaluate,
    load_trajectory,
    run_episode,
    saved_rows,
)
from tests.experiments.evaluation.tiny_runs import comparable
from tests.experiments.own_agents import ConstantAgent, ProportionalAgent

TINY = {
    "env": {"max_steps": 15},
    "agents": {"horizon": 5, "n_scenarios": 5, "n_particles": 300},
}
OWN = "tests.experiments.own_agents"


class BrakingAgent:
    """Defined here, registered nowhere: brakes and keeps the wheel straight; no last_info."""

    name = "braking"

    def __init__(self, config: ExperimentConfig) -> None:
        self.nu = config.make_system().nu
        self.seeds: list[int | None] = []

    def reset(self, seed: int | None = None) -> None:
        self.seeds.append(seed)

    def act(self, obs: Any) -> np.ndarray:
        return np.array([-1.0, 0.0])[: self.nu]


def test_own_agents_in_a_process_pool_equal_the_serial_run(tmp_path):
    agents = [BrakingAgent, f"{OWN}:ProportionalAgent", "nominal"]
    serial = evaluate(agents, [0, 1], TINY, out=tmp_path / "serial", progress=False)
    pool = evaluate(agents, [0, 1], TINY, out=tmp_path / "pool", jobs=2, progress=False)

    assert [r["error"] for r in pool] == [""] * 6
    assert [(r["agent"], r["seed"]) for r in pool] == [
        (a, s) for a in ("braking", "nominal", "proportional") for s in (0, 1)
    ]
    assert comparable(pool) == comparable(serial)
    assert comparable(saved_rows(tmp_path / "pool")) == comparable(serial)
    files = sorted(p.name for p in (tmp_path / "pool" / "episodes").glob("*.json"))
    assert "braking__seed0.json" in files and "proportional__seed1.json" in files
    # The braking agent does what it says: the speed falls at every step it is above 0.
    speed = load_trajectory(tmp_path / "pool", "braking", 0)["true_state"][:, 2]
    assert speed[-1] < speed[0]


def test_own_agents_on_a_local_dask_cluster_equal_the_serial_run(tmp_path):
    pytest.importorskip("distributed")
    # Dask sends factories with cloudpickle: a lambda travels too.
    agents = [BrakingAgent, f"{OWN}:constant_agent_factory", lambda config: BrakingAgent(config)]
    serial = evaluate(agents, [2], TINY, progress=False)
    dask = evaluate(agents, [2], TINY, out=tmp_path, dask_workers=1, progress=False)
    assert [r["error"] for r in dask] == [""] * 3
    assert comparable(dask) == comparable(serial)


def test_a_minimal_agent_has_no_solver_failures_and_na_estimates():
    row, traj = run_episode(BrakingAgent, TINY, seed=3)
    assert row["agent"] == "braking" and row["error"] == "" and row["steps"] == 15
    assert row["solver_failures"] == 0 and row["fallback_steps"] == 0
    assert row["filter_resets"] == 0
    for column in ("latent_rmse", "latent_coverage", "solve_time_median", "slack_total"):
        assert math.isnan(row[column]), column
    assert traj["solver_success"].all() and not traj["fallback"].any()
    assert traj["estimate"].shape == (15, 4) and np.isnan(traj["estimate"]).all()
    assert np.isnan(traj["latent_force_est"]).all()

    # An empty last_info (the constant agent) reads the same way.
    constant, _ = run_episode(f"{OWN}:constant_agent_factory", TINY, seed=3)
    assert constant["agent"] == f"{OWN}.constant_agent_factory"
    assert constant["solver_failures"] == 0 and math.isnan(constant["latent_rmse"])


def test_partial_last_info_is_read_with_its_defaults():
    class HalfInformed(ConstantAgent):
        name = "half_informed"

        def act(self, obs: Any) -> np.ndarray:
            # Reports a solve on even steps only, one failure, and its estimate.
            self.k = getattr(self, "k", -1) + 1
            self.last_info = {"estimate": np.asarray(obs, dtype=float)}
            if self.k % 2 == 0:
                self.last_info.update(solve_time=0.5, success=self.k != 4, slack=1.0)
            return super().act(obs)

    row, traj = run_episode(HalfInformed(np.zeros(2)), TINY, seed=0)
    assert row["solver_failures"] == 1
    assert row["solve_time_median"] == 0.5 and row["slack_total"] == 8.0  # 8 even steps
    assert np.array_equal(traj["estimate"], traj["obs"][:-1])


def test_agent_objects_are_reset_with_the_paired_seed():
    cfg = evaluation.resolve_config(TINY)
    agent = ProportionalAgent(cfg)
    rows = evaluate([agent], [4, 7], TINY, progress=False)
    assert [r["agent"] for r in rows] == ["proportional"] * 2
    assert agent.resets == [agent_seed(4, "proportional"), agent_seed(7, "proportional")]
    assert comparable(rows) == comparable(evaluate([ProportionalAgent], [4, 7], TINY))


def test_a_lambda_runs_serially_and_is_refused_for_a_process_pool(tmp_path, monkeypatch):
    def factory(config):
        return ConstantAgent(np.zeros(2))

    factory.name = "zero"  # type: ignore[attr-defined]
    (row,) = evaluate([factory], [0], TINY, progress=False)
    assert row["agent"] == "zero" and row["error"] == ""
    (row,) = evaluate([lambda config: ConstantAgent(np.zeros(2))], [0], TINY, progress=False)
    assert row["agent"].endswith("_refused_for_a_process_pool.lambda") and row["error"] == ""

    monkeypatch.setattr(evaluation, "_episode_task", None)  # nothing may run
    with pytest.raises(ValueError, match=r"agent '.*<lambda>'.*cannot be sent to worker"):
        evaluate([lambda config: ConstantAgent(np.zeros(2))], [0, 1], TINY, jobs=2)
    assert not (tmp_path / "out").exists()


class Unnamed:
    def __init__(self, config: Any) -> None:
        pass

    def reset(self, seed: int | None = None) -> None:
        pass

    def act(self, obs: Any) -> np.ndarray:
        return np.zeros(2)


def test_names_come_from_the_name_attribute_else_the_spec():
    assert resolve_agent("scenario") is AGENT_REGISTRY["scenario"]
    assert resolve_agent(f"{OWN}:ProportionalAgent").name == "proportional"
    assert resolve_agent(f" {OWN}:ConstantAgent").name == f"{OWN}.ConstantAgent"
    spec = resolve_agent(Unnamed)
    assert isinstance(spec, AgentSpec) and spec.name == "Unnamed" and spec.agent_class is None
    assert isinstance(spec.build(evaluation.resolve_config(TINY)), Agent)


class Named:
    name = "a/b"


class Registered(Unnamed):
    name = "pf"


@pytest.mark.parametrize(
    "agents, match",
    [
        (["nominal", "bogus"], r"unknown agent\(s\) \['bogus'\].*module:attribute"),
        ([f"{OWN}.nope:Agent"], rf"agent '{OWN}.nope:Agent': cannot import module"),
        ([f"{OWN}:Missing"], rf"agent '{OWN}:Missing': module '{OWN}' has no attribute"),
        ([f"{OWN}:NOT_CALLABLE"], r"'NOT_CALLABLE' is a int, neither an agent factory"),
        ([f"{OWN}:not_an_agent_factory"], r"factory returned a str, which has no reset"),
        (["mod:"], r"agent 'mod:': expected 'module:attribute'"),
        ([42], r"unknown agent '42' \(a int\); choose from"),
        ([Named], r"its name 'a/b' must be 1 to 100 letters"),
        ([Registered], r"its name 'pf' is a registered agent's"),
        ([ProportionalAgent, f"{OWN}:ProportionalAgent"], r"\['proportional'\] twice"),
        ([lambda config: 1 / 0], r"calling it with the config raised ZeroDivisionError"),
    ],
)
def test_bad_agent_specs_fail_before_any_episode_naming_the_spec(
    tmp_path, monkeypatch, agents, match
):
    monkeypatch.setattr(evaluation, "_episode_task", None)  # nothing may run
    with pytest.raises(AgentSpecError, match=match) as exc:
        evaluate(agents, [0], TINY, out=tmp_path / "out", progress=False)
    assert "\n" not in str(exc.value)
    assert not (tmp_path / "out").exists()


def test_a_registered_users_agent_runs_by_name_with_its_labels(monkeypatch):
    """A user's agent joins the registry: its name, label and colour are the registered
    agents' kind, and 'module:attribute' of its factory finds the same record."""
    from controllers.agents import registry

    monkeypatch.setattr(registry, "_REGISTERED", dict(registry._REGISTERED))
    monkeypatch.setattr(registry, "AGENT_REGISTRY", registry.MappingProxyType(registry._REGISTERED))
    spec = register_agent("braking", BrakingAgent, label="brakes", colour="black")
    assert registry.AGENT_REGISTRY["braking"] is spec and spec.short_label == "brakes"
    assert list(registry.AGENT_REGISTRY)[-1] == "braking"  # after the project's agents
    assert register_agent("braking", BrakingAgent) is spec  # registered again: the same
    (row,) = evaluate("braking", [0], TINY, progress=False)
    assert row["agent"] == "braking" and row["error"] == ""
    with pytest.raises(AgentSpecError, match="is a registered agent's"):
        register_agent("braking", ProportionalAgent)
    with pytest.raises(AgentSpecError, match="must be 1 to 100 letters"):
        register_agent("a b", ProportionalAgent)
