"""The scenario MPC problem (paper eq. MPCScen) of any latent-force model, independent of solvers.

Every solver (:mod:`controllers.solvers`) solves the same :class:`ScenarioProblem` and returns
an :class:`MPCSolution`; the NumPy methods here (:meth:`ScenarioProblem.rollout`,
:meth:`~ScenarioProblem.objective`, :meth:`~ScenarioProblem.constraint_values`) are the
reference all of them are checked against.

Conventions (shared by every solver), with the dimensions of the model's system:

* ``x0``: initial physical state, shape ``(nx,)`` (same for all scenarios) or ``(Ns, nx)``.
* ``W``: latent force of each scenario along the horizon, ``(Ns, N, nw)``, or ``(Ns, N)``
  when the force has one component; ``W[i, k]`` acts during step ``k``:
  ``x_{k+1} = x_k + dt f(x_k, u_k, W[i, k])``.
* ``u``: the shared input sequence, ``(N, nu)``.
* Objective: the *average* over scenarios of
  ``sum_{k<N} (x_k - x_g)' Q (x_k - x_g) + u_k' R u_k + (x_N - x_g)' Qf (x_N - x_g)``
  plus ``slack_penalty * sum(s)`` (an exact L1 penalty).
* State constraints ``g_j`` of the system apply to ``x_1 ... x_N`` of every scenario; input
  bounds are hard. They are softened by one slack ``s[k, j] >= 0`` per step ``k = 1..N``
  and constraint ``j``, shared by all scenarios: ``g_j(x_k^(i)) <= s[k, j]`` for every
  ``i``. So there are ``ng N`` slacks whatever ``Ns`` is, and at the optimum
  ``s[k, j] = max(0, max_i g_j(x_k^(i)))``: :meth:`ScenarioProblem.objective` evaluates
  exactly this exact-penalty function of ``u``, which every solver must minimise.
* ``backoff`` (optional, per solve): constraint tightening ``b[k, j] >= 0`` in the
  constraints' units, ``(N, ng)`` or ``(ng,)`` for every step; the constraints become
  ``g_j(x_k^(i)) + b[k, j] <= s[k, j]``. Agents use it to keep a margin of ``k`` times the
  estimate's spread along each constraint (:mod:`controllers.agents.mpc`).

**Feedback prediction** (``prediction="feedback"``; ``"open_loop"``, the default, is the
paper's formulation above). Scenario ``i`` applies ``u_{i,0} = v_0`` and, for ``k >= 1``,
``u_{i,k} = v_k + K_k (x_k^(i) - r_k)`` with the shared decision ``v`` ``(N, nu)`` and a
:class:`~controllers.feedback_law.FeedbackLaw` ``(K, r)`` frozen during a solve (``K_0 = 0``: the
first input is applied now, before any scenario's deviation is known). The objective is the
scenario average of ``sum_k (x_k - x_g)' Q (x_k - x_g) + u_{i,k}' R u_{i,k}`` plus the
terminal cost, plus ``slack_penalty`` times the state slacks (as above) and the *input
slacks*: the per-scenario input bounds ``lo <= u_{i,k} <= hi`` of ``k = 1..N-1`` are
softened like the state constraints, one slack per (step, input, side) shared by the
scenarios, ``s^u[k, i, +] = max(0, max_s u_{s,k,i} - hi_i)`` (``2 nu (N-1)`` slacks whatever
``Ns`` is). ``v_0`` stays inside the input bounds (it is applied now); the fast SQP leaves ``v_k``
(``k >= 1``) free by default, the other solvers bound it too
(``FastSolverOptions.feedback_bounds``). The reference methods take the law as ``law=``;
without it (or for an open-loop problem) they are the open-loop functions, unchanged. With
``K = 0`` the feedback objective equals the open-loop one. The fast SQP solves it natively
(:mod:`controllers.solvers.fast.closed_loop`), the other solvers through an exact rewrite
(:mod:`controllers.solvers.feedback`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from controllers.feedback_law import FeedbackLaw
from lfm_env.cost import QuadraticCost
from lfm_env.model import LatentForceModel
from lfm_env.system import ControlSystem

#: The predictions of a scenario problem (``ScenarioProblem.prediction``).
PREDICTIONS = ("open_loop", "feedback")


@runtime_checkable
class PredictionModel(Protocol):
    """What a scenario problem needs of its model: the system, the step and the Euler step.

    :class:`~lfm_env.model.LatentForceModel` is one; :class:`EulerModel` is the minimal one
    (a system and ``dt``, no latent-force prior), used where the forces are plain data, as
    in the feedback rewrite of :mod:`controllers.solvers.feedback`.
    """

    system: ControlSystem
    dt: float

    def physical_step(self, x: np.ndarray, u: np.ndarray, w: np.ndarray) -> np.ndarray:
        """``x + dt f(x, u, w)`` of states ``(..., nx)``."""
        ...


@dataclass(frozen=True, eq=False)
class EulerModel:
    """A system and its sampling time, nothing else: a :class:`PredictionModel` without a
    latent-force prior (the forces ``W`` of a solve are data).

    Args:
        system: the controlled system.
        dt: sampling time [s], ``> 0``.
    """

    system: ControlSystem
    dt: float

    def __post_init__(self) -> None:
        if not isinstance(self.system, ControlSystem):
            raise ValueError(f"EulerModel.system={self.system!r}: must be a ControlSystem")
        dt = self.dt
        if isinstance(dt, bool) or not isinstance(dt, (int, float, np.integer, np.floating)):
            raise ValueError(f"EulerModel.dt={dt!r}: must be a number of seconds > 0")
        if not (math.isfinite(dt) and dt > 0):
            raise ValueError(f"EulerModel.dt={dt!r}: must be a finite number of seconds > 0")
        object.__setattr__(self, "dt", float(dt))

    def physical_step(self, x: np.ndarray, u: np.ndarray, w: np.ndarray) -> np.ndarray:
        """Euler step ``x + dt f(x, u, w)`` of states ``(..., nx)`` (the system's own)."""
        return self.system.euler_step(x, u, w, self.dt)


@dataclass(frozen=True, eq=False)
class ScenarioProblem:
    """Data of a scenario MPC problem; everything that does not change between steps.

    Args:
        model: the latent-force model (its system gives dynamics, bounds and constraints,
            its ``dt`` the step); any :class:`PredictionModel` (e.g. :class:`EulerModel`).
        cost: the quadratic cost on the goal.
        horizon: ``N``, prediction steps.
        n_scenarios: ``Ns``.
        slack_penalty: exact L1 penalty per unit of total constraint slack.
        prediction: ``"open_loop"`` (one shared input sequence, the paper's) or
            ``"feedback"`` (the shared decision plus a frozen feedback law per solve; see
            the module docstring).
    """

    model: LatentForceModel | PredictionModel
    cost: QuadraticCost
    horizon: int = 7
    n_scenarios: int = 150
    slack_penalty: float = 1.0e4
    prediction: str = "open_loop"

    def __post_init__(self) -> None:
        def check(name: str, ok: bool, allowed: str) -> None:
            if not ok:
                raise ValueError(
                    f"ScenarioProblem.{name}={getattr(self, name)!r}: must be {allowed}"
                )

        def is_int(v: object) -> bool:
            return isinstance(v, (int, np.integer)) and not isinstance(v, bool)

        def is_number(v: object) -> bool:
            return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool)

        check(
            "model",
            isinstance(self.model, LatentForceModel)
            or (
                isinstance(self.model, PredictionModel)
                and isinstance(self.model.system, ControlSystem)
            ),
            "a LatentForceModel (or a PredictionModel: system, dt, physical_step)",
        )
        check("cost", isinstance(self.cost, QuadraticCost), "a QuadraticCost")
        self.cost.check_system(self.model.system)
        check("horizon", is_int(self.horizon) and self.horizon >= 1, "an int >= 1")
        check("n_scenarios", is_int(self.n_scenarios) and self.n_scenarios >= 1, "an int >= 1")
        check("slack_penalty", is_number(self.slack_penalty), "a real number")
        check("slack_penalty", np.isfinite(self.slack_penalty) and self.slack_penalty > 0, "> 0")
        check("prediction", self.prediction in PREDICTIONS, f"one of {PREDICTIONS}")

    # ------------------------------------------------------------------ dimensions

    @property
    def system(self):
        """The controlled system (:class:`~lfm_env.system.ControlSystem`)."""
        return self.model.system

    @property
    def dt(self) -> float:
        """Sampling time [s]."""
        return self.model.dt

    @property
    def nx(self) -> int:
        return self.model.system.nx

    @property
    def nu(self) -> int:
        return self.model.system.nu

    @property
    def nw(self) -> int:
        return self.model.system.nw

    @property
    def ng(self) -> int:
        return self.model.system.ng

    @property
    def input_lower(self) -> np.ndarray:
        """Lower input bounds ``(nu,)``."""
        return self.model.system.input_lower

    @property
    def input_upper(self) -> np.ndarray:
        """Upper input bounds ``(nu,)``."""
        return self.model.system.input_upper

    # ------------------------------------------------------------------ data

    def check_data(self, x0: np.ndarray, W: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Validate and broadcast ``x0`` to ``(Ns, nx)`` and ``W`` to ``(Ns, N, nw)``."""
        x0 = _as_float_array(x0, "x0")
        W = _as_float_array(W, "W")
        ns, n, nx, nw = self.n_scenarios, self.horizon, self.nx, self.nw
        if nw == 1 and W.shape == (ns, n):
            W = W[:, :, None]
        if W.shape != (ns, n, nw):
            expected = f"(n_scenarios, horizon, nw) = {(ns, n, nw)}"
            if nw == 1:
                expected += f" or {(ns, n)}"
            raise ValueError(f"W has shape {W.shape}; expected {expected}")
        if x0.shape == (nx,):
            x0 = np.broadcast_to(x0, (ns, nx))
        if x0.shape != (ns, nx):
            raise ValueError(f"x0 has shape {x0.shape}; expected ({nx},) or {(ns, nx)}")
        if not (np.all(np.isfinite(x0)) and np.all(np.isfinite(W))):
            raise ValueError("x0 and W must be finite (no NaN or inf)")
        return x0, W

    def check_backoff(self, backoff: np.ndarray | None) -> np.ndarray | None:
        """``None``, or the back-off as a finite ``(N, ng)`` array ``>= 0`` (from ``(ng,)``)."""
        if backoff is None:
            return None
        b = _as_float_array(backoff, "backoff")
        n, ng = self.horizon, self.ng
        if b.shape == (ng,):
            b = np.broadcast_to(b, (n, ng))
        if b.shape != (n, ng) or not np.all(np.isfinite(b)) or np.any(b < 0.0):
            raise ValueError(
                f"backoff has shape {b.shape} or entries that are negative or not finite; "
                f"expected finite values >= 0 of shape (horizon, ng) = {(n, ng)} or ({ng},)"
            )
        return b

    def check_inputs(self, u: np.ndarray, name: str = "u") -> np.ndarray:
        """``u`` as a finite ``(N, nu)`` float array, or a ValueError naming ``name``."""
        u = _as_float_array(u, name)
        shape = (self.horizon, self.nu)
        if u.size == self.horizon * self.nu and u.ndim == 1:
            u = u.reshape(shape)
        if u.shape != shape or not np.all(np.isfinite(u)):
            raise ValueError(
                f"{name} has shape {u.shape} or non-finite entries; "
                f"expected finite (horizon, nu) = {shape}"
            )
        return u

    # ------------------------------------------------------------------ reference functions

    def check_law(self, law: FeedbackLaw | None) -> FeedbackLaw | None:
        """``None``, or ``law`` checked against this problem's shapes.

        Raises:
            ValueError: a law for an open-loop problem, or one of the wrong shape.
        """
        if law is None:
            return None
        if self.prediction != "feedback":
            raise ValueError(
                f"law given for a problem with prediction={self.prediction!r}; a feedback law "
                "needs ScenarioProblem(..., prediction='feedback')"
            )
        if not isinstance(law, FeedbackLaw):
            raise ValueError(f"law must be a controllers.feedback_law.FeedbackLaw, got {law!r}")
        return law.check(self)

    def rollout(
        self, x0: np.ndarray, W: np.ndarray, u: np.ndarray, law: FeedbackLaw | None = None
    ) -> np.ndarray:
        """Predicted states ``(Ns, N+1, nx)`` of every scenario under inputs ``u`` ``(N, nu)``
        (the decision ``v`` with a feedback ``law``)."""
        if self.check_law(law) is not None:
            return self._feedback_rollout(x0, W, u, law)[0]
        x0, W = self.check_data(x0, W)
        u = np.asarray(u, dtype=float).reshape(self.horizon, self.nu)
        X = np.empty((self.n_scenarios, self.horizon + 1, self.nx))
        X[:, 0] = x0
        for k in range(self.horizon):
            X[:, k + 1] = self.model.physical_step(X[:, k], u[k], W[:, k])
        return X

    def inputs(
        self, x0: np.ndarray, W: np.ndarray, u: np.ndarray, law: FeedbackLaw | None = None
    ) -> np.ndarray:
        """The inputs ``(Ns, N, nu)`` every scenario applies: ``u`` itself in open loop, the
        law's ``v_k + K_k (x_{s,k} - r_k)`` (``v_0`` at ``k = 0``) with a feedback ``law``."""
        if self.check_law(law) is not None:
            return self._feedback_rollout(x0, W, u, law)[1]
        u = np.asarray(u, dtype=float).reshape(self.horizon, self.nu)
        return np.broadcast_to(u, (self.n_scenarios, self.horizon, self.nu)).copy()

    def _feedback_rollout(
        self, x0: np.ndarray, W: np.ndarray, v: np.ndarray, law: FeedbackLaw
    ) -> tuple[np.ndarray, np.ndarray]:
        """States ``(Ns, N+1, nx)`` and inputs ``(Ns, N, nu)`` under the feedback law."""
        x0, W = self.check_data(x0, W)
        v = np.asarray(v, dtype=float).reshape(self.horizon, self.nu)
        X = np.empty((self.n_scenarios, self.horizon + 1, self.nx))
        U = np.empty((self.n_scenarios, self.horizon, self.nu))
        X[:, 0] = x0
        U[:, 0] = v[0]
        for k in range(self.horizon):
            if k:
                U[:, k] = v[k] + (X[:, k] - law.r[k]) @ law.K[k].T
            X[:, k + 1] = self.model.physical_step(X[:, k], U[:, k], W[:, k])
        return X, U

    def input_slack(self, U: np.ndarray) -> np.ndarray:
        """The least input slacks ``(N-1, nu, 2)`` of per-scenario inputs ``U`` ``(Ns, N, nu)``:
        ``[k-1, i, 0] = max(0, max_s U[s, k, i] - hi_i)`` and ``[k-1, i, 1] = max(0, lo_i -
        min_s U[s, k, i])`` for steps ``k = 1..N-1``, in the inputs' units."""
        U = np.asarray(U, dtype=float)[:, 1:]
        upper = np.maximum(np.max(U - self.input_upper, axis=0, initial=-np.inf), 0.0)
        lower = np.maximum(np.max(self.input_lower - U, axis=0, initial=-np.inf), 0.0)
        return np.stack([upper, lower], axis=-1)

    def constraint_values(self, X: np.ndarray, backoff: np.ndarray | None = None) -> np.ndarray:
        """Constraint values ``g + b <= 0`` ``(Ns, N, ng)`` of predicted states, steps 1..N."""
        g = np.asarray(self.system.constraint_values(X[:, 1:]))
        b = self.check_backoff(backoff)
        return g if b is None else g + b

    def constraint_violation(self, X: np.ndarray, backoff: np.ndarray | None = None) -> float:
        """Largest state-constraint violation over all scenarios and steps (0 if none)."""
        g = self.constraint_values(X, backoff)
        return float(max(np.max(g, initial=0.0), 0.0))

    def minimal_slack(self, X: np.ndarray, backoff: np.ndarray | None = None) -> np.ndarray:
        """The smallest feasible slacks ``s[k, j] = max(0, max_i g_j + b)``, ``(N, ng)``."""
        g = self.constraint_values(X, backoff)
        return np.maximum(np.max(g, axis=0, initial=-np.inf), 0.0)

    def objective(
        self,
        x0: np.ndarray,
        W: np.ndarray,
        u: np.ndarray,
        backoff: np.ndarray | None = None,
        law: FeedbackLaw | None = None,
    ) -> float:
        """Exact-penalty objective of inputs ``u``: the reference every solver minimises.

        Scenario-averaged quadratic cost plus ``slack_penalty * sum(minimal_slack)``, with
        the constraints tightened by ``backoff`` when given. With a feedback ``law`` (a
        feedback problem only): the objective of the decision ``u`` (= ``v``) of the module
        docstring, with the per-scenario input cost and the input slacks.
        """
        if self.check_law(law) is not None:
            return self._feedback_objective(x0, W, u, backoff, law)
        X = self.rollout(x0, W, u)
        slack = float(np.sum(self.minimal_slack(X, backoff)))
        u = np.asarray(u, dtype=float).reshape(self.horizon, self.nu)
        cost = self.cost
        stage = np.sum(cost.state_cost(X[:, :-1]), axis=1)
        terminal = cost.terminal_cost(X[:, -1])
        inputs = float(np.sum(cost.input_cost(u)))
        return float(np.mean(stage + terminal) + inputs + self.slack_penalty * slack)

    def _feedback_objective(
        self,
        x0: np.ndarray,
        W: np.ndarray,
        v: np.ndarray,
        backoff: np.ndarray | None,
        law: FeedbackLaw,
    ) -> float:
        X, U = self._feedback_rollout(x0, W, v, law)
        slack = float(np.sum(self.minimal_slack(X, backoff))) + float(np.sum(self.input_slack(U)))
        cost = self.cost
        stage = np.sum(cost.state_cost(X[:, :-1]), axis=1) + np.sum(cost.input_cost(U), axis=1)
        terminal = cost.terminal_cost(X[:, -1])
        return float(np.mean(stage + terminal) + self.slack_penalty * slack)


def _as_float_array(value: object, name: str) -> np.ndarray:
    """``value`` as a float array, or a ValueError naming ``name`` (text, objects, complex)."""
    arr = np.asarray(value)
    if arr.dtype.kind not in "biuf":
        raise ValueError(f"{name} must be an array of finite real numbers, got dtype {arr.dtype}")
    return arr.astype(float, copy=False)


@dataclass
class MPCSolution:
    """What a solve returns.

    ``success`` says the solver converged; ``usable`` says the plan may be applied: it is
    finite and the solver's merit is below that of its warm start (true after any accepted
    step of a merit-decreasing solver, and for every converged solve). A solve that stops
    early (iteration or time limit, a failed line search or QP) with a usable plan keeps
    its solver's status (e.g. ``"Maximum_Iterations_Exceeded"``) and ``success=False``;
    agents apply its plan (they count it as an unconverged solve). A solve without a usable
    plan is a failure: agents fall back. ``usable`` defaults to ``success``.
    """

    u: np.ndarray  # (N, nu) optimal shared input sequence (feedback: the decision v)
    objective: float  # scenario-averaged cost plus slack penalty
    slack: float  # sum of the slacks s[k, j]; 0 when the hard problem is feasible
    status: str  # solver's return status, e.g. "Solve_Succeeded"
    success: bool  # True when the solver reports convergence
    solve_time: float  # [s] wall time of the solve
    iterations: int  # solver iterations
    predicted: np.ndarray | None = None  # (Ns, N+1, nx) predicted states under u
    extra: dict = field(default_factory=dict)  # solver-specific statistics
    usable: bool | None = None  # the plan may be applied (None: the same as success)
    law: FeedbackLaw | None = None  # feedback: the law of this solve
    nominal_u: np.ndarray | None = None  # feedback: (N, nu) inputs of the nominal scenario

    def __post_init__(self) -> None:
        if self.usable is None:
            self.usable = bool(self.success)
        self.usable = bool(self.usable) and bool(np.all(np.isfinite(self.u)))

    @property
    def plan(self) -> np.ndarray:
        """The inputs ``(N, nu)`` an agent keeps: ``nominal_u`` of a feedback solve (what it
        applies along its nominal scenario), else ``u``. ``plan[0] == u[0]``."""
        return self.u if self.nominal_u is None else self.nominal_u


def is_usable(success: bool, merit: float, start_merit: float) -> bool:
    """:attr:`MPCSolution.usable` from a solve's outcome: converged, or a finite merit
    strictly below the warm start's (``start_merit``, the same merit function)."""
    return bool(success) or (math.isfinite(merit) and merit < start_merit)


def largest_local_descent(
    problem: ScenarioProblem,
    x0: np.ndarray,
    W: np.ndarray,
    u: np.ndarray,
    radii: tuple[float, ...] = (1e-5, 1e-3),
    n_random: int = 40,
    seed: int = 0,
) -> float:
    """The lowest change of :meth:`ScenarioProblem.objective` found next to ``u`` (``>= 0``:
    none lower).

    A solver-independent check of local optimality: ``u`` is moved along every input
    coordinate in both directions and along ``n_random`` random directions (unit norm),
    by each radius in ``radii`` (in the inputs' units), clipped to the input bounds, and
    the full objective (every scenario, every constraint, the exact slack penalty) is
    evaluated there. A local minimiser gives a change ``>= 0`` up to rounding (about
    ``1e-12 |objective|``); a point that is not one almost always shows a clear descent.

    Returns:
        ``min(objective(u') - objective(u))`` over the probed points ``u'``.
    """
    u = np.asarray(u, dtype=float)
    base = problem.objective(x0, W, u)
    n_u = u.size
    rng = np.random.default_rng(seed)
    directions = np.concatenate([np.eye(n_u), -np.eye(n_u), rng.standard_normal((n_random, n_u))])
    directions[2 * n_u :] /= np.linalg.norm(directions[2 * n_u :], axis=1, keepdims=True)
    lower = np.broadcast_to(problem.input_lower, u.shape)
    upper = np.broadcast_to(problem.input_upper, u.shape)
    lowest = np.inf
    for radius in radii:
        for d in directions:
            trial = np.clip(u + radius * d.reshape(u.shape), lower, upper)
            lowest = min(lowest, problem.objective(x0, W, trial) - base)
    return float(lowest)


__all__ = [
    "PREDICTIONS",
    "EulerModel",
    "MPCSolution",
    "PredictionModel",
    "ScenarioProblem",
    "is_usable",
    "largest_local_descent",
]
