"""Agents of a user's own, for the tests of evaluating agents that are not registered.

Importable as ``tests.experiments.own_agents`` (``lfm-evaluate --agents
tests.experiments.own_agents:ProportionalAgent`` from the repository root). None of them
is in :data:`controllers.agents.registry.AGENT_REGISTRY`; they follow
:class:`controllers.agents.protocol.Agent`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from controllers.config import ExperimentConfig


class ProportionalAgent:
    """Steers towards the goal's lateral position and holds a cruise speed; no last_info.

    A minimal agent: ``reset`` and ``act`` only, built from the config (its constructor
    is the factory). On the sine track: ``a = k_v (v_ref - v)``,
    ``delta = k_y (y_goal - p_y) - k_psi psi``, clipped to the input bounds.
    """

    name = "proportional"

    def __init__(self, config: ExperimentConfig) -> None:
        self.system = config.make_system()
        self.goal = np.asarray(config.make_cost().x_goal, dtype=float)
        self.resets: list[int | None] = []

    def reset(self, seed: int | None = None) -> None:
        self.resets.append(seed)

    def act(self, obs: Any) -> np.ndarray:
        p_y, v, psi = float(obs[1]), float(obs[2]), float(obs[3])
        u = np.array([0.5 * (1.0 - v), 0.3 * (self.goal[1] - p_y) - 0.5 * psi])
        return self.system.clip_input(u)


def constant_agent_factory(config: ExperimentConfig) -> ConstantAgent:
    """A factory function: a :class:`ConstantAgent` applying zero inputs."""
    return ConstantAgent(np.zeros(config.make_system().nu))


class ConstantAgent:
    """Applies one constant action; its ``last_info`` is an empty dict."""

    def __init__(self, action: np.ndarray) -> None:
        self.action = np.asarray(action, dtype=float)
        self.last_info: dict[str, Any] = {}

    def reset(self, seed: int | None = None) -> None:
        self.last_info = {}

    def act(self, obs: Any) -> np.ndarray:
        return self.action.copy()


NOT_CALLABLE = 42  # for the test of a 'module:attribute' that is no factory


def not_an_agent_factory(config: ExperimentConfig) -> str:
    """A factory returning something without reset and act."""
    return "not an agent"
