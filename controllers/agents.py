"""MPC agents for the SineTrack world, all with the same face.

Every agent has ``reset(seed=None)``, ``act(obs) -> action`` and ``last_info`` (a
dict: solve time [s], solver status, iterations, slack, state estimate and its
standard deviation, latent-force estimate, the plan and the predicted trajectories).

* :class:`NominalMPCAgent`: the observation taken as the state, no latent force in its
  model (``w = 0``), one deterministic prediction.
* :class:`CertaintyEquivalentMPCAgent` (``"pf"``): particle-filter estimate; predicts the
  latent force by its mean ``H A^k z``; one noise-free scenario.
* :class:`ScenarioMPCAgent` (``"scenario"``): particle filter plus the scenario MPC of the
  paper: ``Ns`` draws of the latent process noise over the horizon, one shared input
  sequence.
* :class:`OracleMPCAgent` (``"oracle"``): an upper bound, NOT a controller one can build:
  it reads the true state and the true future disturbance from the env.

Agents draw their randomness from their own seed, independent of the env's, so the
same env seed gives every agent the same disturbance and noise.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any

import numpy as np

from controllers import problem as mpc_problem
from controllers.config import AgentConfig
from controllers.estimators.particle_filter import ParticleFilter, gaussian_log_likelihood
from controllers.problem import MPCSolution, ScenarioProblem
from lfm_env.config import ConfigError, EnvConfig, check_latent_step
from lfm_env.model import LatentForceModel, psd_factor
from lfm_env.validation import real_vector

# chi^2 quantile with 4 degrees of freedom at 1 - 1e-6: a measurement this far from
# every particle means the filter has diverged.
_DIVERGENCE_NIS = 33.4


def make_problem(env_config: EnvConfig, cfg: AgentConfig, n_scenarios: int) -> ScenarioProblem:
    """The scenario MPC problem from the known model (env section) and agent settings."""
    return ScenarioProblem(
        horizon=cfg.horizon,
        n_scenarios=n_scenarios,
        dt=env_config.dt,
        vehicle_length=env_config.vehicle_length,
        Q=cfg.Q,
        R=cfg.R,
        Qf=cfg.Qf,
        x_goal=tuple(cfg.goal_state_rad.tolist()),
        track=env_config.track,
        speed_min=env_config.speed_min,
        speed_max=env_config.speed_max,
        accel_max=env_config.accel_max,
        steer_max=env_config.steer_max,
        slack_penalty=cfg.slack_penalty,
    )


def make_solver(problem: ScenarioProblem, cfg: AgentConfig):
    """The scenario solver named by ``cfg.solver``, built once."""
    if cfg.solver == "fast":
        from controllers.solvers.fast import FastScenarioSolver

        return FastScenarioSolver(problem, max_iter=cfg.max_iter)
    from controllers.solvers.ipopt import IpoptScenarioSolver

    formulation = "multiple_shooting" if cfg.solver == "ipopt_multiple_shooting" else "condensed"
    return IpoptScenarioSolver(problem, formulation, ipopt_options={"max_iter": cfg.max_iter})


class MPCAgent:
    """Common receding-horizon loop: estimate, build scenarios, solve, apply ``u_0``.

    Subclasses implement :meth:`_estimate` (the state estimate from the observation) and
    :meth:`_scenarios` (``x0`` and ``W`` for the solver).
    """

    name = "mpc"
    n_scenarios = 1

    def __init__(self, env_config: EnvConfig, cfg: AgentConfig) -> None:
        self.env_config = env_config
        self.cfg = cfg
        self.model = LatentForceModel(env_config, cfg.disturbance)
        self.problem = make_problem(env_config, cfg, self.n_scenarios)
        self.mpc = make_solver(self.problem, cfg)
        self.last_info: dict[str, Any] = {}
        self.rng = np.random.default_rng()
        self._u_prev: np.ndarray | None = None
        self._plan: np.ndarray | None = None  # remaining planned inputs (fallback)

    # ------------------------------------------------------------------ public face

    def reset(self, seed: int | None = None) -> None:
        """Start a new episode; ``seed`` fixes the agent's own randomness."""
        self.rng = np.random.default_rng(seed)
        self.mpc.reset()
        self._u_prev = None
        self._plan = None
        self.last_info = {}

    def act(self, obs: Any) -> np.ndarray:
        """The action ``[a m/s^2, delta rad]`` for observation ``obs`` ``[m, m, m/s, rad]``."""
        y = real_vector(obs, 4, "obs", "[p_x m, p_y m, v m/s, psi rad]")
        t0 = time.perf_counter()
        info = self._estimate(y)
        t_est = time.perf_counter() - t0
        x0, W = self._scenarios()
        sol = self.mpc.solve(x0, W)
        u, fallback = self._choose_action(sol)
        self._u_prev = u
        info.update(
            solve_time=sol.solve_time,
            estimate_time=t_est,
            status=sol.status,
            success=bool(sol.success),
            iterations=int(sol.iterations),
            solver_extra=dict(sol.extra or {}),
            slack=float(sol.slack),
            objective=float(sol.objective),
            fallback=fallback,
            plan=sol.u.copy(),
            predicted=None if sol.predicted is None else sol.predicted[:, :, :].copy(),
            x0=np.asarray(x0, dtype=float).copy(),
            W=np.asarray(W).copy(),
        )
        self.last_info = info
        return u

    # ------------------------------------------------------------------ internals

    def _choose_action(self, sol: MPCSolution) -> tuple[np.ndarray, str]:
        """First input of a good plan; otherwise the previous plan shifted, or braking."""
        lo, hi = self.problem.input_lower, self.problem.input_upper
        if sol.success and np.all(np.isfinite(sol.u)):
            self._plan = np.clip(sol.u, lo, hi)
            return self._plan[0].copy(), ""
        if self._plan is not None and len(self._plan) > 1:
            self._plan = self._plan[1:]
            return self._plan[0].copy(), "previous_plan"
        self._plan = None
        return np.array([-self.problem.accel_max, 0.0]), "brake"

    def _estimate(self, y: np.ndarray) -> dict[str, Any]:
        raise NotImplementedError

    def _scenarios(self) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError


class NominalMPCAgent(MPCAgent):
    """Classical MPC: the observation is the state, the latent force is ignored (``w = 0``)."""

    name = "nominal"

    def _estimate(self, y: np.ndarray) -> dict[str, Any]:
        self._x = y
        return {"estimate": y.copy(), "estimate_std": np.zeros(4)}

    def _scenarios(self) -> tuple[np.ndarray, np.ndarray]:
        return self._x, np.zeros((1, self.problem.horizon))


class _FilteringAgent(MPCAgent):
    """An agent that estimates physical and latent states with a bootstrap particle filter."""

    def __init__(self, env_config: EnvConfig, cfg: AgentConfig) -> None:
        super().__init__(env_config, cfg)
        self._meas_std = env_config.measurement_std_rad
        self._log_lik = gaussian_log_likelihood(self._meas_std, [0, 1, 2, 3])
        self._latent_cov_factor = psd_factor(self.model.stationary_latent_covariance())
        self.pf: ParticleFilter | None = None
        self.n_filter_resets = 0

    def reset(self, seed: int | None = None) -> None:
        super().reset(seed)
        self.pf = None
        self.n_filter_resets = 0

    def _prior(self, y: np.ndarray) -> np.ndarray:
        """Physical states around the first measurement, latent states stationary."""
        n, p = self.cfg.n_particles, self.model.latent_dim
        x = y + self.rng.standard_normal((n, 4)) * self._meas_std
        z = self.rng.standard_normal((n, p)) @ self._latent_cov_factor.T
        return np.concatenate([x, z], axis=1)

    def _estimate(self, y: np.ndarray) -> dict[str, Any]:
        if self.pf is None:
            self.pf = ParticleFilter(
                self.model.transition,
                self._log_lik,
                self._prior(y),
                self.rng,
                resampling=self.cfg.resampling,
                ess_threshold=self.cfg.ess_threshold,
            )
            degenerate = False
        else:
            rec = self.pf.step(self._u_prev, y)
            degenerate = bool(rec.degenerate)
        # Divergence check: if even the closest particle explains y worse than a
        # 1e-6 tail event, the cloud has lost the car (sample impoverishment can pin it
        # far from the truth); restart from the prior around y and say so.
        diverged = degenerate or self._closest_nis(y) > _DIVERGENCE_NIS
        if diverged:
            self.pf.reset(self._prior(y))
            self.n_filter_resets += 1
        mean, std = self.pf.mean, self.pf.std
        cov = self.pf.covariance
        H = self.model.H
        w_mean = float(mean[4:] @ H)
        w_std = float(np.sqrt(max(H @ cov[4:, 4:] @ H, 0.0)))
        self._mean = mean
        return {
            "estimate": mean.copy(),
            "estimate_std": std.copy(),
            "latent_force": w_mean,
            "latent_force_std": w_std,
            "filter_degenerate": degenerate,
            "filter_reset": diverged,
            "filter_resets": self.n_filter_resets,
        }

    def _closest_nis(self, y: np.ndarray) -> float:
        """Smallest normalised innovation ``sum(((x_i - y) / std)^2)`` over particles."""
        r = (self.pf.particles[:, :4] - y) / self._meas_std
        return float(np.min(np.einsum("ij,ij->i", r, r)))


class CertaintyEquivalentMPCAgent(_FilteringAgent):
    """PF + MPC: the latent force predicted by its mean ``H A^k z_hat``; one scenario."""

    name = "pf"

    def _scenarios(self) -> tuple[np.ndarray, np.ndarray]:
        x0 = self._mean[:4]
        W = self.model.mean_latent_forecast(self._mean[4:], self.problem.horizon)
        return x0, W.reshape(1, -1)


class ScenarioMPCAgent(_FilteringAgent):
    """The paper's method: PF estimate plus scenario MPC over sampled latent-force paths."""

    name = "scenario"

    def __init__(self, env_config: EnvConfig, cfg: AgentConfig) -> None:
        self.n_scenarios = cfg.scenario_count()
        super().__init__(env_config, cfg)

    def _scenarios(self) -> tuple[np.ndarray, np.ndarray]:
        ns = self.problem.n_scenarios
        if self.cfg.scenario_initial_states == "particles":
            # The paper's remark: initial states drawn from the filter's distribution.
            idx = self.rng.choice(self.pf.n_particles, size=ns, p=self.pf.weights)
            start = self.pf.particles[idx]
            x0, z0 = start[:, :4], start[:, 4:]
        else:
            x0 = self._mean[:4]
            z0 = np.broadcast_to(self._mean[4:], (ns, self.model.latent_dim))
        W = self.model.sample_latent_forecasts(z0, self.problem.horizon, self.rng)
        return x0, W


class ParticleScenarioMPCAgent(ScenarioMPCAgent):
    """Scenario MPC whose scenarios also start from the filter's particles (paper's remark).

    Each scenario's initial physical and latent state is a particle drawn by weight, so
    the plan also respects the estimate's uncertainty, not only the future noise.
    """

    name = "scenario_particles"

    def __init__(self, env_config: EnvConfig, cfg: AgentConfig) -> None:
        super().__init__(env_config, dataclasses.replace(cfg, scenario_initial_states="particles"))


class OracleMPCAgent(MPCAgent):
    """UPPER BOUND, not a realisable controller: reads the true state and future force.

    It gets the env (``make_agent("oracle", env=env)``) and reads
    ``env.unwrapped.true_state`` and ``env.unwrapped.preview_disturbance(N)``, which do
    not change the episode. The observation passed to :meth:`act` is ignored.
    """

    name = "oracle"

    def __init__(self, env_config: EnvConfig, cfg: AgentConfig, env: Any) -> None:
        if env is None:
            raise ValueError("the oracle agent needs env=... (it reads the hidden truth)")
        super().__init__(env_config, cfg)
        self.env = env

    def _estimate(self, y: np.ndarray) -> dict[str, Any]:
        truth = self.env.unwrapped
        self._x = truth.true_state
        self._W = truth.preview_disturbance(self.problem.horizon).reshape(1, -1)
        return {"estimate": self._x.copy(), "estimate_std": np.zeros(4)}

    def _scenarios(self) -> tuple[np.ndarray, np.ndarray]:
        return self._x, self._W


AGENTS = {
    "nominal": NominalMPCAgent,
    "pf": CertaintyEquivalentMPCAgent,
    "scenario": ScenarioMPCAgent,
    "scenario_particles": ParticleScenarioMPCAgent,
    "oracle": OracleMPCAgent,
}

AGENT_LABELS = {
    "nominal": "nominal MPC (w = 0)",
    "pf": "PF + certainty-equivalent MPC",
    "scenario": "PF + scenario MPC (paper)",
    "scenario_particles": "PF + scenario MPC, scenarios start from particles (paper's remark)",
    "oracle": "oracle MPC (upper bound, reads hidden truth)",
}


def check_agent_config(name: str, env_config: EnvConfig, cfg: AgentConfig | None = None) -> None:
    """Raise ``ConfigError`` if agent ``name`` cannot run on this (valid) world.

    Cheap (builds nothing), so :func:`experiments.evaluation.evaluate` calls it for
    every agent before the first episode. The particle filter of the ``pf`` and
    ``scenario`` agents weighs measurements by their noise, which must not be zero, and
    the agents' own model of the force (``cfg.disturbance``) must have a stable step.
    """
    if cfg is not None and cfg.disturbance is not None:
        check_latent_step(env_config, cfg.disturbance, where="agents.disturbance")
    std = env_config.measurement_noise_std
    if name in ("pf", "scenario") and not all(s > 0.0 for s in std):
        raise ConfigError(
            f"env.measurement_noise_std={list(std)}: must be all > 0 for the {name!r} agent "
            "(its particle filter weighs each measurement by this noise)"
        )


def make_agent(name: str, config: Any = None, env: Any = None) -> MPCAgent:
    """Build an agent by name.

    Args:
        name: one of ``"nominal"``, ``"pf"``, ``"scenario"``, ``"scenario_particles"``,
            ``"oracle"``.
        config: a YAML path, a dict (whole file), or ``None`` for the paper's values; the
            ``env`` section is the agents' known model, the ``agents`` section their settings.
        env: the environment, only for the oracle (which reads the hidden truth).
    """
    from controllers.config import load_agent_config
    from lfm_env.config import load_env_config

    if name not in AGENTS:
        raise ValueError(f"unknown agent {name!r}; choose one of {sorted(AGENTS)}")
    if env is not None and name != "oracle":
        raise ValueError(f"agent {name!r} must not get env= (only the oracle reads the truth)")
    env_config = check_latent_step(load_env_config(config))
    cfg = load_agent_config(config)
    check_agent_config(name, env_config, cfg)
    if name == "oracle":
        return OracleMPCAgent(env_config, cfg, env)
    return AGENTS[name](env_config, cfg)


__all__ = ["AGENTS", "AGENT_LABELS", "check_agent_config", "make_agent", "mpc_problem"]
