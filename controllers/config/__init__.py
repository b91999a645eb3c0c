"""Typed, validated configuration of the agents and of a whole experiment: the one place a
config file is read.

:func:`load_config` (the resolver) reads a whole config (a preset's name, a path, a dict:
``env_id``, ``env``, ``agents``, ``evaluation``, with ``base:`` and ``--set`` overrides) into an
:class:`ExperimentConfig`, which builds, once, what the agents need: their model of the
world (:meth:`ExperimentConfig.make_model`), their cost (:meth:`~ExperimentConfig.make_cost`)
and the scenario problem (:meth:`~ExperimentConfig.make_problem`).

* :mod:`controllers.config.sections`: the ``agents:`` and ``evaluation:`` sections
  (:class:`AgentConfig`, :class:`RobustConfig`, :class:`EvaluationConfig`) and the memory
  estimates;
* :mod:`controllers.config.experiment`: reading a whole config, and
  :class:`ExperimentConfig`.

The world's ``env:`` section is the world's own (:mod:`lfm_env.config`).
"""

from controllers.config.experiment import (
    DEFAULT_PRESET,
    TOP_LEVEL_KEYS,
    ExperimentConfig,
    apply_overrides,
    load_config,
    merge,
    read_document,
)
from controllers.config.sections import (
    DEFAULT_EPISODE_TIMEOUT,
    FAST_MAX_HORIZON,
    MEMORY_BUDGET,
    AgentConfig,
    EvaluationConfig,
    RobustConfig,
    check_filter_memory,
    check_problem_memory,
)
from controllers.solvers import SOLVERS
from lfm_env.config import ConfigError

__all__ = [
    "DEFAULT_EPISODE_TIMEOUT",
    "DEFAULT_PRESET",
    "FAST_MAX_HORIZON",
    "MEMORY_BUDGET",
    "SOLVERS",
    "TOP_LEVEL_KEYS",
    "AgentConfig",
    "ConfigError",
    "EvaluationConfig",
    "ExperimentConfig",
    "RobustConfig",
    "apply_overrides",
    "check_filter_memory",
    "check_problem_memory",
    "load_config",
    "merge",
    "read_document",
]
