"""Configs built in Python get the checks a file gets (issue 35, item 8): lists and arrays
read like the file's lists, one-line errors naming the field, and a back-off of the wrong
length refused when the agent is built, not at its first ``act()``."""

from __future__ import annotations

import numpy as np
import pytest

from controllers.agents.mpc import RobustMPCAgent, ScenarioMPCAgent
from controllers.config import AgentConfig, ConfigError, RobustConfig, load_config


@pytest.mark.parametrize(
    "field, value", [("Q", [1, 1, 1, 0]), ("R", np.array([0.5, 10.0])), ("backoff", 2)]
)
def test_python_lists_and_arrays_are_read_like_the_files_lists(field, value):
    settings = AgentConfig(**{field: value})
    assert getattr(settings, field) == tuple(float(v) for v in np.atleast_1d(value))
    hash(settings)  # still a frozen, hashable config


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"Q": "big"}, r"Q='big': expected a list"),
        ({"Q": [1, "a", 1, 0]}, r"Q\[1\]='a': expected a number"),
        ({"robust": {"backoff": [1, -1]}}, r"backoff=\(1.0, -1.0\): must be in \[0, 10\]"),
        ({"robust": {"estimatr": "ukf"}}, r"unknown config key\(s\) \['robust.estimatr'\]"),
    ],
)
def test_bad_python_values_are_config_errors_naming_the_field(kwargs, message):
    with pytest.raises(ConfigError, match=message):
        AgentConfig(**kwargs)


def test_a_backoff_of_the_wrong_length_is_refused_when_the_agent_is_built():
    cfg = load_config("quick")
    settings = AgentConfig(n_particles=100, n_scenarios=5, backoff=(1.0, 2.0))  # 3 groups
    with pytest.raises(ConfigError, match=r"agents.backoff=\[1.0, 2.0\]: must be one number or 3"):
        ScenarioMPCAgent(cfg.make_model(), cfg.make_cost(), settings, cfg.measurement_std)
    robust = AgentConfig(n_particles=100, robust=RobustConfig(backoff=(1.0, 2.0)))
    with pytest.raises(ConfigError, match=r"agents.robust.backoff=\[1.0, 2.0\]"):
        RobustMPCAgent(cfg.make_model(), cfg.make_cost(), robust, cfg.measurement_std)
