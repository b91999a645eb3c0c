"""MPC agents over any latent-force model, all with the same face.

Every agent has ``reset(seed=None)``, ``act(obs) -> action`` and ``last_info`` (a dict:
solve time [s], solver status, iterations, slack, state estimate and its standard
deviation, latent-force estimate, the plan and the predicted trajectories). An agent is
built from a :class:`~lfm_env.model.LatentForceModel` (its belief about the world: the
system, the latent force's kernel, the noise), a :class:`~lfm_env.cost.QuadraticCost`,
its :class:`~controllers.config.AgentConfig` and the std of the measurement noise of the
full-state observation ``y = x + e``; every dimension is read from the model.

* :class:`NominalMPCAgent` (``"nominal"``): the observation taken as the state, no latent
  force in its model (``w = 0``), one deterministic prediction.
* :class:`CertaintyEquivalentMPCAgent` (``"pf"``): particle-filter estimate; predicts the
  latent force by its mean ``H A^k z``; one noise-free scenario.
* :class:`ScenarioMPCAgent` (``"scenario"``): particle filter plus the scenario MPC of the
  paper: ``Ns`` draws of the latent process noise over the horizon, all from the
  estimate's mean, one shared input sequence.
* :class:`ParticleScenarioMPCAgent` (``"scenario_particles"``): the same, with each
  scenario starting from a particle (the paper's remark): the plan also carries the
  estimate's uncertainty.
* :class:`OracleMPCAgent` (``"oracle"``): certainty-equivalent MPC that reads the truth
  (the true state and the true future latent force, from the env): a reference no
  controller can be built as, but not an upper bound (its short horizon plans no margin,
  and it can violate or fail where an agent with margins does not).

With ``settings.prediction == "feedback"`` every agent's scenario problem is the feedback
one (:mod:`controllers.feedback_law`): its solver (``make_solver`` on that problem,
:class:`~controllers.solvers.feedback.FeedbackScenarioSolver`) keeps the reference plan (the
nominal inputs of its last usable plan, shifted), computes the law from it at every step
(at the first step, and after a solve without a usable plan, from an open-loop solve of the
same problem) and returns the decision, whose first input is applied; the agent keeps the
plan's nominal inputs as its fallback plan. With one scenario (``nominal``, ``pf``,
``oracle``, ``robust`` with ``forecast: mean``) the feedback only re-parametrises the plan.

Agents draw their randomness from their own seed, independent of the env's, so the
same env seed gives every agent the same latent force and noise. Every agent here follows
:class:`controllers.agents.protocol.Agent` and has stable-baselines3's ``predict``
(:class:`controllers.agents.protocol.SB3Predict`); an agent of one's own needs only the protocol.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any

import numpy as np

from controllers.agents.estimation import EstimatorLoop
from controllers.agents.protocol import SB3Predict
from controllers.config import (
    AgentConfig,
    ConfigError,
    check_filter_memory,
    check_problem_memory,
)
from controllers.estimators.estimator import make_estimator
from controllers.problem import MPCSolution, ScenarioProblem
from controllers.solvers import make_solver
from lfm_env.cost import QuadraticCost
from lfm_env.model import LatentForceModel
from lfm_env.validation import real_vector


class PlanChoice:
    """What every MPC agent does with a solve (a mixin): the action it applies and the step's
    ``last_info`` values of the solve. The agent owns ``self.system``, ``self.model`` (its
    ``dt``) and ``self._x_hat`` (the step's state estimate) and keeps ``self._plan``."""

    def _choose_action(self, sol: MPCSolution) -> tuple[np.ndarray, str]:
        """First input of a usable plan (:attr:`MPCSolution.usable`: converged, or stopped
        early below its warm start); otherwise the previous plan shifted, or the system's
        fallback at the state estimate (the bicycle brakes to a standstill). The plan kept
        is :attr:`MPCSolution.plan` (a feedback plan's nominal inputs)."""
        if sol.usable:
            self._plan = self.system.clip_input(sol.plan)
            return self._plan[0].copy(), ""
        if self._plan is not None and len(self._plan) > 1:
            self._plan = self._plan[1:]
            return self._plan[0].copy(), "previous_plan"
        self._plan = None
        return self.system.fallback(self._x_hat, self.model.dt), "fallback"

    @staticmethod
    def _solve_info(
        sol: MPCSolution,
        estimate_time: float,
        fallback: str,
        x0: Any,
        W: Any,
        backoff: np.ndarray | None = None,
    ) -> dict[str, Any]:
        """The ``last_info`` values of a solve: its times [s], status, success and usability,
        iterations, statistics, slack, objective, the fallback used, the plan, the predicted
        states and the solve's data (``x0``, ``W``, ``backoff``), copied."""
        return {
            "solve_time": sol.solve_time,
            "estimate_time": estimate_time,
            "status": sol.status,
            "success": bool(sol.success),
            "usable": bool(sol.usable),
            "iterations": int(sol.iterations),
            "solver_extra": dict(sol.extra or {}),
            "slack": float(sol.slack),
            "objective": float(sol.objective),
            "fallback": fallback,
            "plan": sol.plan.copy(),
            "predicted": None if sol.predicted is None else sol.predicted.copy(),
            "x0": np.asarray(x0, dtype=float).copy(),
            "W": np.array(W, dtype=float),
            "backoff": None if backoff is None else backoff.copy(),
        }


class MPCAgent(PlanChoice, SB3Predict):
    """Common receding-horizon loop: estimate, build scenarios, solve, apply ``u_0``.

    An :class:`~controllers.agents.protocol.Agent` with every ``last_info`` key, and with
    stable-baselines3's ``predict`` (:class:`~controllers.agents.protocol.SB3Predict`), so
    ``evaluate_policy(agent, env)`` runs it. Subclasses implement :meth:`_estimate` (the
    state estimate from the observation) and :meth:`_scenarios` (``x0`` and ``W`` for the
    solver).

    Args:
        model: the agent's latent-force model of the world.
        cost: the control objective (stage, terminal and input weights, goal state).
        settings: horizon, scenario count, particle count, solver, ... (paper values by
            default).
        measurement_std: std of the noise of each observed state, in the states' units
            ``(nx,)``; used by the filtering agents' likelihood and prior.
    """

    name = "mpc"
    uses_scenarios = False  # True: Ns scenarios from settings; False: one scenario
    needs_measurement_noise = False  # True: its estimator needs every noise std > 0

    def __init__(
        self,
        model: LatentForceModel,
        cost: QuadraticCost,
        settings: AgentConfig | None = None,
        measurement_std: Any = None,
    ) -> None:
        self.model = model
        self.system = model.system
        self.cost = cost
        self.settings = AgentConfig() if settings is None else settings
        nx = self.system.nx
        std = np.zeros(nx) if measurement_std is None else measurement_std
        self.measurement_std = real_vector(
            std, nx, "measurement_std", f"one per state {list(self.system.state_names)}"
        )
        n_scenarios = self.settings.scenario_count(self.system.nu) if self.uses_scenarios else 1
        check_problem_memory(model, self.settings.horizon, n_scenarios)
        self.problem = ScenarioProblem(
            model,
            cost,
            horizon=self.settings.horizon,
            n_scenarios=n_scenarios,
            slack_penalty=self.settings.slack_penalty,
            prediction=self.settings.prediction,
        )
        # A solve that reaches max_solve_time fails, and _choose_action falls back.
        threads = self.settings.solver_threads
        self.solver = make_solver(
            self.problem,
            self.settings.solver,
            max_iter=self.settings.max_iter,
            max_time=self.settings.max_solve_time,
            **({"threads": threads} if threads > 1 else {}),
        )
        # agents.deadline: the step budget [s] (None: none), enforced through the solver's
        # per-solve time limit.
        self._deadline = self.settings.deadline_seconds(model.dt)
        # [s] how far a stopped solve ran past its limit (the solver checks it between
        # iterations): kept back from the next budgets, so that steps end by the deadline.
        self._overrun = 0.0
        if self._deadline is not None and not hasattr(self.solver, "set_max_time"):
            raise ConfigError(
                f"agents.deadline={self.settings.deadline!r}: solver {self.settings.solver!r} "
                "takes no per-solve time limit; use solver 'fast' or 'fast_c', or deadline null"
            )
        self.last_info: dict[str, Any] = {}
        self.rng = np.random.default_rng()
        self._u_prev: np.ndarray | None = None
        self._plan: np.ndarray | None = None  # remaining planned inputs (fallback)
        self._rti_ready = False  # a usable plan to take real-time iterations from

    # ------------------------------------------------------------------ public face

    def reset(self, seed: int | None = None) -> None:
        """Start a new episode; ``seed`` fixes the agent's own randomness."""
        self.rng = np.random.default_rng(seed)
        self.solver.reset()
        self._overrun = 0.0
        self._u_prev = None
        self._plan = None
        self._rti_ready = False
        self.last_info = {}

    def act(self, obs: Any) -> np.ndarray:
        """The action ``(nu,)`` in the inputs' units for an observation ``(nx,)`` of the state."""
        y = real_vector(obs, self.system.nx, "obs", f"{list(self.system.state_names)}")
        t0 = time.perf_counter()
        info = self._estimate(y)
        t_est = time.perf_counter() - t0
        self._x_hat = np.asarray(info["estimate"][: self.system.nx], dtype=float)
        x0, W = self._scenarios()
        backoff = self._backoff()
        sol, iterations, limit = self._solve(x0, W, backoff, t0)
        u, fallback = self._choose_action(sol)
        # The budget stopped this solve: what the agent applied instead of a converged plan.
        stopped = limit is not None and sol.status == "Maximum_WallTime_Exceeded"
        if stopped:  # the largest recent overrun, decaying
            self._overrun = max(sol.solve_time - limit, 0.8 * self._overrun, 0.0)
        deadline_stop = (fallback or "plan") if stopped else ""
        self._u_prev = u
        info.update(self._solve_info(sol, t_est, fallback, x0, W, backoff))
        info["deadline_stop"] = deadline_stop
        info["sqp_iterations"] = iterations
        self.last_info = info
        return u

    # ------------------------------------------------------------------ internals

    def _solve(
        self, x0: np.ndarray, W: np.ndarray, backoff: np.ndarray | None, t0: float
    ) -> tuple[MPCSolution, str, float | None]:
        """The step's solve (the step started at ``t0``), how its iterations went
        (``last_info["sqp_iterations"]``) and its time limit from the deadline
        (:meth:`_limit_solve`): ``"converged"``; with ``settings.iterations == "rti"`` and a
        usable plan from the last step, ``"rti"`` (``settings.rti_iterations`` SQP iterations
        from that plan shifted), or ``"rti_fallback:<why>"`` when that step was bad
        (:func:`rti_step_problem`) and the problem was solved again to convergence from it,
        within what the step has left (the times and iterations of both solves counted)."""
        kwargs = {} if backoff is None else {"backoff": backoff}
        limit = self._limit_solve(t0)
        if self.settings.iterations != "rti" or not self._rti_ready:
            sol = self.solver.solve(x0, W, **kwargs)
            self._rti_ready = bool(sol.usable)
            return sol, "converged", limit
        rti = self.solver.solve(x0, W, iterations=self.settings.rti_iterations, **kwargs)
        why = rti_step_problem(rti)
        if not why:
            return rti, "rti", limit
        if rti.law is not None:  # (a feedback plan: the same law, from the RTI iterate)
            kwargs["law"] = rti.law
        limit = self._limit_solve(t0)
        sol = self.solver.solve(x0, W, u_guess=rti.u, **kwargs)
        sol.solve_time += rti.solve_time
        sol.iterations += rti.iterations
        self._rti_ready = bool(sol.usable)
        return sol, f"rti_fallback:{why}", limit

    def _limit_solve(self, t0: float) -> float | None:
        """With ``agents.deadline``: give the solve what the step has left of its budget, less
        the recent overrun of stopped solves (at least a microsecond: the solver then
        returns its warm start, not usable, and the agent falls back). Returns that limit
        [s] when it is below ``agents.max_solve_time``, else ``None``."""
        if self._deadline is None:
            return None
        left = self._deadline - (time.perf_counter() - t0) - self._overrun
        limit = min(self.settings.max_solve_time, max(left, 1e-6))
        self.solver.set_max_time(limit)
        return limit if limit < self.settings.max_solve_time else None

    def _backoff(self) -> np.ndarray | None:
        """Constraint tightening ``(ng,)`` for this solve; ``None`` for none (the default)."""
        return None

    def _no_force(self) -> np.ndarray:
        """``W = 0`` for one scenario ``(1, N, nw)``."""
        return np.zeros((1, self.problem.horizon, self.system.nw))

    def _estimate(self, y: np.ndarray) -> dict[str, Any]:
        raise NotImplementedError

    def _scenarios(self) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError


def rti_step_problem(sol: MPCSolution, slack_tol: float = 1e-6) -> str:
    """Why a real-time iteration's plan is not to be applied, or ``""``: ``"not_usable"`` (its
    merit did not fall below that of the plan shifted by one step, ``extra["start_merit"]``),
    or ``"slack"`` (its slack grew beyond the shifted plan's, ``extra["start_slack"]``, by
    more than ``slack_tol`` times ``1 + `` that slack, in the constraints' units)."""
    if not sol.usable:
        return "not_usable"
    start = float(sol.extra.get("start_slack", np.inf))
    if sol.slack > start + slack_tol * (1.0 + start):
        return "slack"
    return ""


class NominalMPCAgent(MPCAgent):
    """Classical MPC: the observation is the state, the latent force is ignored (``w = 0``)."""

    name = "nominal"

    def _estimate(self, y: np.ndarray) -> dict[str, Any]:
        self._x = y
        return {"estimate": y.copy(), "estimate_std": np.zeros(self.system.nx)}

    def _scenarios(self) -> tuple[np.ndarray, np.ndarray]:
        return self._x, self._no_force()


class _FilteringAgent(EstimatorLoop, MPCAgent):
    """An agent that estimates physical and latent states with ``settings.estimator``.

    Built like :class:`MPCAgent`; ``measurement_std`` must be all > 0. The estimator is one
    of :data:`controllers.estimators.estimator.ESTIMATORS` (the paper's bootstrap particle
    filter by default).
    """

    needs_measurement_noise = True

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        if not np.all(self.measurement_std > 0.0):
            raise ValueError(
                f"measurement_std={self.measurement_std.tolist()}: must be all > 0 for the "
                f"{self.name!r} agent (its estimator weighs each measurement by this noise)"
            )
        s = self.settings
        # k_j per constraint, once: a back-off of the wrong length is refused here, not at act().
        self._factors = self._backoff_factors
        where = "agents.robust.n_particles" if self.name == "robust" else "agents.n_particles"
        check_filter_memory(self.model, s.n_particles, s.estimator, where)
        self.estimator = make_estimator(
            s.estimator,
            self.model,
            self.measurement_std,
            n_particles=s.n_particles,
            resampling=s.resampling,
            ess_threshold=s.ess_threshold,
        )
        self._init_estimator_loop()

    def reset(self, seed: int | None = None) -> None:
        super().reset(seed)
        self._init_estimator_loop()

    def _estimate(self, y: np.ndarray) -> dict[str, Any]:
        info, self._mean, self._cov = self._estimator_step(y)
        return info

    def _mean_forecast_scenario(self) -> tuple[np.ndarray, np.ndarray]:
        """One scenario: the estimate's mean, the force's mean forecast ``H A^k z_hat``."""
        nx = self.system.nx
        W = self.model.mean_latent_forecast(self._mean[nx:], self.problem.horizon)
        return self._mean[:nx], W[None]

    def _backoff(self) -> np.ndarray | None:
        """``settings.backoff`` times the estimate's std along each constraint's gradient.

        ``b_j = k_j sqrt(dg_j(x_hat)' Sigma_x dg_j(x_hat))`` with the physical block
        ``Sigma_x`` of the estimate's covariance, the same at every step of the horizon;
        ``k_j`` is the one value of ``settings.backoff`` or that of ``g_j``'s constraint group.
        """
        k = self._factors
        if k is None:
            return None
        nx = self.system.nx
        J = self.system.constraint_jacobian(self._mean[:nx])  # (ng, nx)
        spread = np.einsum("ji,ik,jk->j", J, self._cov[:nx, :nx], J)
        return k * np.sqrt(np.maximum(spread, 0.0))

    @property
    def _backoff_factors(self) -> np.ndarray | None:
        """``k_j`` per constraint ``(ng,)``, or ``None`` when no constraint is backed off."""
        factors = tuple(self.settings.backoff)
        system = self.system
        if system.ng == 0 or not any(f > 0.0 for f in factors):
            return None
        if len(factors) == 1:
            return np.full(system.ng, factors[0])
        groups = system.constraint_groups
        if len(factors) != len(groups):
            where = "agents.robust.backoff" if self.name == "robust" else "agents.backoff"
            raise ConfigError(
                f"{where}={list(factors)}: must be one number or {len(groups)}, one per "
                f"constraint group {list(groups)} of the {system.name} system"
            )
        k = np.zeros(system.ng)
        for f, members in zip(factors, groups.values(), strict=True):
            k[list(members)] = f
        return k


class CertaintyEquivalentMPCAgent(_FilteringAgent):
    """PF + MPC: the latent force predicted by its mean ``H A^k z_hat``; one scenario."""

    name = "pf"

    def _scenarios(self) -> tuple[np.ndarray, np.ndarray]:
        return self._mean_forecast_scenario()


class ScenarioMPCAgent(_FilteringAgent):
    """The paper's method: PF estimate plus scenario MPC over sampled latent-force paths.

    With ``settings.scenario_initial_states == "particles"`` every scenario starts from a
    particle drawn by weight (the paper's remark); by default all start from the mean.
    """

    name = "scenario"
    uses_scenarios = True
    initial_states: str | None = None  # None: settings.scenario_initial_states

    def _scenarios(self) -> tuple[np.ndarray, np.ndarray]:
        ns, nx = self.problem.n_scenarios, self.system.nx
        if (self.initial_states or self.settings.scenario_initial_states) == "particles":
            start = self.estimator.sample(ns, self.rng)
            x0, z0 = start[:, :nx], start[:, nx:]
        else:
            x0 = self._mean[:nx]
            z0 = np.broadcast_to(self._mean[nx:], (ns, self.model.latent_dim))
        W = self.model.sample_latent_forecasts(z0, self.problem.horizon, self.rng)
        return x0, W


class ParticleScenarioMPCAgent(ScenarioMPCAgent):
    """Scenario MPC whose scenarios also start from the filter's particles (paper's remark).

    Each scenario's initial physical and latent state is a particle drawn by weight, so
    the plan also respects the estimate's uncertainty, not only the future noise.
    """

    name = "scenario_particles"
    initial_states = "particles"


class RobustMPCAgent(ScenarioMPCAgent):
    """The uncertainty-aware agent: ``settings.robust`` (:class:`RobustConfig`) chooses its
    estimator, constraint back-off and forecast, the rest is the ``agents`` section's.

    With ``forecast="mean"`` it plans one scenario with the force's mean forecast (as the
    ``pf`` agent) inside constraints backed off by the estimate's spread; with
    ``"sampled"`` it is the scenario agent with the same back-off.
    """

    name = "robust"

    def __init__(
        self,
        model: LatentForceModel,
        cost: QuadraticCost,
        settings: AgentConfig | None = None,
        measurement_std: Any = None,
    ) -> None:
        base = AgentConfig() if settings is None else settings
        r = base.robust
        n_scenarios = 1 if r.forecast == "mean" else (r.n_scenarios or base.n_scenarios)
        merged = dataclasses.replace(
            base,
            estimator=r.estimator,
            n_particles=r.n_particles,
            backoff=r.backoff,
            n_scenarios=n_scenarios,
            scenario_initial_states=r.scenario_initial_states,
        )
        super().__init__(model, cost, merged, measurement_std)

    def _scenarios(self) -> tuple[np.ndarray, np.ndarray]:
        if self.settings.robust.forecast == "mean":
            return self._mean_forecast_scenario()
        return super()._scenarios()


class OracleMPCAgent(MPCAgent):
    """Certainty-equivalent MPC that reads the truth: the true state and future force.

    Not a controller one can build, and not an upper bound: it plans one scenario, the
    true force over its horizon, with no margin, so what lies beyond the horizon or
    between the samples can still make it violate or fail where an agent with margins
    does not. It gets the env (``make_agent("oracle", env=env)``) and reads
    ``env.unwrapped.true_state`` and ``env.unwrapped.preview_latent_force(N)``, which do
    not change the episode. The observation passed to :meth:`act` is ignored.
    """

    name = "oracle"

    def __init__(
        self,
        model: LatentForceModel,
        cost: QuadraticCost,
        settings: AgentConfig | None = None,
        measurement_std: Any = None,
        env: Any = None,
    ) -> None:
        if env is None:
            raise ValueError("the oracle agent needs env=... (it reads the hidden truth)")
        super().__init__(model, cost, settings, measurement_std)
        self.env = env

    def _estimate(self, y: np.ndarray) -> dict[str, Any]:
        truth = self.env.unwrapped
        self._x = np.asarray(truth.true_state, dtype=float)
        self._W = np.asarray(truth.preview_latent_force(self.problem.horizon), dtype=float)[None]
        return {"estimate": self._x.copy(), "estimate_std": np.zeros(self.system.nx)}

    def _scenarios(self) -> tuple[np.ndarray, np.ndarray]:
        return self._x, self._W


__all__ = [
    "rti_step_problem",
    "CertaintyEquivalentMPCAgent",
    "MPCAgent",
    "PlanChoice",
    "NominalMPCAgent",
    "OracleMPCAgent",
    "ParticleScenarioMPCAgent",
    "RobustMPCAgent",
    "ScenarioMPCAgent",
]
