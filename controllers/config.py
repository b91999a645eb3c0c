"""Typed, validated configuration of the agents (the ``agents:`` section of a config file)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from lfm_env.config import ConfigError, DisturbanceConfig, _Checker, from_dict, read_section

SOLVERS = ("fast", "ipopt", "ipopt_multiple_shooting")
RESAMPLING = ("systematic", "stratified", "residual", "multinomial")
SCENARIO_INITIAL_STATES = ("estimate", "particles")
MAX_SCENARIOS = 100_000
MAX_ITER = 2**31 - 1


@dataclass(frozen=True)
class AgentConfig:
    """Settings shared by the MPC agents (paper values by default).

    The agents' *model* of the world (dynamics, bounds, GP hyperparameters, noise levels)
    is the ``env`` section: it is the known structure the paper gives the controller.
    Vectors over the state give the heading in degrees, as in the ``env`` section.
    """

    horizon: int = 7  # N, prediction steps
    n_scenarios: int | None = 150  # Ns; null to derive it from violation_level/confidence
    violation_level: float | None = None  # epsilon of the Campi-Garatti bound, in (0, 1)
    confidence: float | None = None  # beta of the Campi-Garatti bound, in (0, 1)
    n_particles: int = 7000  # particle filter size
    resampling: str = "systematic"  # one of RESAMPLING
    ess_threshold: float | None = None  # null: resample every step (paper); else in (0, 1]
    Q: tuple[float, float, float, float] = (2.0, 2.0, 1.0, 0.0)  # stage weights on x - x_g
    Qf: tuple[float, float, float, float] = (2.0, 2.0, 1.0, 0.0)  # terminal weights
    R: tuple[float, float] = (0.5, 10.0)  # input weights on [a, delta (rad)]
    goal_state: tuple[float, float, float, float] = (62.83, 0.0, 4.0, 0.0)  # [m, m, m/s, deg]
    slack_penalty: float = 1.0e4  # exact L1 penalty per unit of state-constraint slack
    solver: str = "fast"  # fast (condensed SQP), ipopt (condensed), ipopt_multiple_shooting
    max_iter: int = 100  # solver iteration limit per step
    scenario_initial_states: str = "estimate"  # "estimate" (paper) or "particles" (its remark)
    # The agents' belief about the latent force. null: the env section's, known a priori
    # (the paper); set it to learned hyperparameters (see lfm-calibrate).
    disturbance: DisturbanceConfig | None = None

    def __post_init__(self) -> None:
        c = _Checker(self)
        c("horizon", self.horizon >= 1, "an integer >= 1")
        c("horizon", self.horizon <= 200, "<= 200")
        if self.n_scenarios is None:
            c(
                "n_scenarios",
                self.violation_level is not None and self.confidence is not None,
                "an integer >= 1, or null with violation_level and confidence set",
            )
        else:
            c("n_scenarios", 1 <= self.n_scenarios <= MAX_SCENARIOS, "an integer in [1, 100000]")
        for name in ("violation_level", "confidence"):
            v = getattr(self, name)
            c(name, v is None or 0.0 < v < 1.0, "null or in (0, 1)")
        if self.n_scenarios is None:
            # The Campi-Garatti count must fit the same range as an explicit one; its
            # bound decreases in Ns, so checking it at the largest count suffices.
            from scipy import optimize, stats

            def excess(eps: float) -> float:
                return stats.binom.cdf(2 * self.horizon - 1, MAX_SCENARIOS, eps) - self.confidence

            if excess(self.violation_level) > 0.0:
                least = optimize.brentq(excess, self.violation_level, 1.0 - 1e-9)
                least *= 1.001  # shown rounded to 4 digits: round up, so that it is admissible
                c(
                    "violation_level",
                    False,
                    f">= {least:.4g} with confidence={self.confidence} and horizon={self.horizon}"
                    f" (the Campi-Garatti scenario count must stay <= {MAX_SCENARIOS})",
                )
        c("n_particles", 1 <= self.n_particles <= 10_000_000, "an integer in [1, 1e7]")
        c("resampling", self.resampling in RESAMPLING, f"one of {RESAMPLING}")
        c(
            "ess_threshold",
            self.ess_threshold is None or 0.0 < self.ess_threshold <= 1.0,
            "null or in (0, 1]",
        )
        c.non_negative("Q", "Qf", "R")
        c.positive("slack_penalty")
        c("solver", self.solver in SOLVERS, f"one of {SOLVERS}")
        # IPOPT's iteration counter is a C int: larger values wrap around or are refused.
        c("max_iter", 1 <= self.max_iter <= MAX_ITER, f"an integer in [1, {MAX_ITER}]")
        c(
            "scenario_initial_states",
            self.scenario_initial_states in SCENARIO_INITIAL_STATES,
            f"one of {SCENARIO_INITIAL_STATES}",
        )

    @property
    def goal_state_rad(self) -> np.ndarray:
        """Goal state of the cost ``[m, m, m/s, rad]``."""
        g = np.array(self.goal_state, dtype=float)
        g[3] = math.radians(g[3])
        return g

    def scenario_count(self) -> int:
        """``n_scenarios``, or the Campi-Garatti count for ``2 N`` decision variables."""
        if self.n_scenarios is not None:
            return self.n_scenarios
        from controllers.solvers.ipopt import campi_garatti_scenarios

        return campi_garatti_scenarios(self.violation_level, self.confidence, 2 * self.horizon)


def load_agent_config(config: Any = None) -> AgentConfig:
    """An :class:`AgentConfig` from a path, a dict (whole file or its ``agents`` section),
    an ``AgentConfig`` or ``None`` (paper defaults)."""
    if isinstance(config, AgentConfig):
        return config
    if hasattr(config, "agents") and isinstance(config.agents, AgentConfig):
        return config.agents
    section = read_section(config, "agents")
    return from_dict(AgentConfig, section, prefix="agents")


__all__ = ["AgentConfig", "ConfigError", "load_agent_config", "SOLVERS"]
