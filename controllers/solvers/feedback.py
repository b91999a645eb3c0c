"""The registered solvers on the feedback scenario problem, through an exact rewrite.

``make_solver(problem, name)`` on a problem with ``prediction="feedback"`` returns, for every
solver but the fast SQP (which solves it natively: :mod:`controllers.solvers.fast.closed_loop`;
this rewrite is its test oracle, and its fallback where no C compiler works), a
:class:`FeedbackScenarioSolver`: it rewrites the feedback problem (the module docstring of
:mod:`controllers.problem`) as an ordinary open-loop :class:`ScenarioProblem` on an
augmented system (:func:`augmented_problem`), solves that with the registered solver
``name`` (unchanged: the fast SQP and its C library, IPOPT, ``sqpmethod``, csnlp) and maps
the plan back. The rewrite is exact: its objective equals
:meth:`ScenarioProblem.objective` with the law for every decision inside the input bounds.

For any :class:`~lfm_env.system.ControlSystem` ``f(x, u, w)`` (``nx, nu, nw, ng``) and a
:class:`~controllers.feedback_law.FeedbackLaw` ``(K, r)``:

* state ``x' = [x, y]`` (``nx + nu``): ``y_{k+1} = u_{s,k}``, the input scenario ``s``
  applied at step ``k`` (``y_0 = 0``);
* input ``v`` (``nu``): the shared decision, with the system's input bounds (so ``v_0``,
  applied now, is hard-bounded, and so is every nominal input ``v_k``);
* force ``w' = [w, vec K_k, r_k]`` (``nw + nu nx + nx``): the solvers treat forces as fixed
  data of a solve, and the frozen law rides along, step by step;
* ``f'(x', v, w') = [f(x, u, w), (u - y) / dt]`` with ``u = v + K_k (x - r_k)`` (``K_0 = 0``:
  ``u_{s,0} = v_0``), so the model's Euler step gives ``y_{k+1} = u_{s,k}``;
* constraints ``g' = [g(x), y - hi, lo - y]``: the per-scenario input bounds as state
  constraints of step ``k + 1``, softened by the same shared slack and penalty as the
  state constraints (those of ``y_1 = v_0`` are never violated);
* cost ``Q' = diag(Q, R)``, ``Qf' = diag(Qf, R)``, ``R' = 0``: the term ``y' R y`` of step
  ``k + 1`` is the scenario's own input cost ``u_{s,k}' R u_{s,k}``.

The augmented problem's model is an :class:`~controllers.problem.EulerModel` (the system and
``dt``): its forces are data, with no latent-force prior to invent for the gains.

What this costs against a native implementation: ``nu nx + nx`` more force values per point
(12 for the bicycle, 18 for the quadrotor) and ``nu`` more states; the solvers' structure
detection finds no shared linear rows in the augmented system (the feedback makes every
row depend on the scenario).
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from controllers.feedback_law import (
    FeedbackLaw,
    feedback_law,
    nominal_inputs,
    reference_plan,
    shifted,
)
from controllers.problem import EulerModel, MPCSolution, ScenarioProblem
from lfm_env.cost import QuadraticCost
from lfm_env.system import ControlSystem, split_unit
from lfm_env.xp import xp

if TYPE_CHECKING:
    from controllers.solvers import ScenarioSolver, SolverSpec


@dataclass(frozen=True)
class ClosedLoopRhs:
    """``f'(x', v, w')`` of the module docstring, for NumPy batches and CasADi (picklable)."""

    system: ControlSystem
    dt: float

    def __call__(self, xa: Any, v: Any, wa: Any) -> Any:
        s = self.system
        nx, nu, nw = s.nx, s.nu, s.nw
        xs, vs, ws = xp.unstack(xa), xp.unstack(v), xp.unstack(wa)
        x, y = xs[:nx], xs[nx:]
        gains = ws[nw : nw + nu * nx]  # K_k row-major (nu, nx)
        e = [x[j] - ws[nw + nu * nx + j] for j in range(nx)]  # x - r_k
        u = []
        for i in range(nu):
            ui = vs[i]
            for j in range(nx):
                ui = ui + gains[i * nx + j] * e[j]
            u.append(ui)
        dx = xp.unstack(s.rhs(xp.stack(x), xp.stack(u), xp.stack(ws[:nw])))
        return xp.stack(list(dx) + [(u[i] - y[i]) / self.dt for i in range(nu)])


@dataclass(frozen=True)
class ClosedLoopConstraints:
    """``g'(x') = [g(x), y - hi, lo - y]`` of the module docstring (picklable)."""

    system: ControlSystem

    def __call__(self, xa: Any) -> Any:
        s = self.system
        xs = xp.unstack(xa)
        x, y = xs[: s.nx], xs[s.nx :]
        parts = list(xp.unstack(s.constraint_values(xp.stack(x)))) if s.ng else []
        lo, hi = s.input_lower, s.input_upper
        parts += [y[i] - float(hi[i]) for i in range(s.nu)]
        parts += [float(lo[i]) - y[i] for i in range(s.nu)]
        return xp.stack(parts)


def augmented_problem(problem: ScenarioProblem) -> ScenarioProblem:
    """The open-loop problem equivalent to the feedback ``problem`` (module docstring)."""
    s, cost = problem.system, problem.cost
    nx, nu = s.nx, s.nu
    labels = [split_unit(n) for n in s.input_names]
    rows = [
        f"{name}_{side}" + (f" [{unit}]" if unit else "")
        for side in ("upper", "lower")
        for name, unit in labels
    ]
    system = ControlSystem(
        name=f"{s.name}_feedback",
        state_names=tuple(s.state_names) + tuple(f"applied_{n}" for n in s.input_names),
        input_names=tuple(f"nominal_{n}" for n in s.input_names),
        rhs=ClosedLoopRhs(s, float(problem.dt)),
        input_lower=s.input_lower,
        input_upper=s.input_upper,
        constraints=ClosedLoopConstraints(s),
        constraint_names=tuple(s.constraint_names) + tuple(rows),
        force_names=tuple(s.force_names)
        + tuple(f"K_{i}_{j} [-]" for i in range(nu) for j in range(nx))
        + tuple(f"r_{j} [-]" for j in range(nx)),
        mirror_inputs=s.mirror_inputs,
    )
    zero = np.zeros((nx, nu))
    aug_cost = QuadraticCost(
        Q=np.block([[cost.Q, zero], [zero.T, cost.R]]),
        Qf=np.block([[cost.Qf, zero], [zero.T, cost.R]]),
        R=np.zeros((nu, nu)),
        x_goal=np.concatenate([cost.x_goal, np.zeros(nu)]),
    )
    return ScenarioProblem(
        EulerModel(system, problem.dt),
        aug_cost,
        horizon=problem.horizon,
        n_scenarios=problem.n_scenarios,
        slack_penalty=problem.slack_penalty,
    )


def augmented_data(
    problem: ScenarioProblem, x0: np.ndarray, W: np.ndarray, law: FeedbackLaw
) -> tuple[np.ndarray, np.ndarray]:
    """``x0'`` ``(Ns, nx + nu)`` and ``W'`` ``(Ns, N, nw + nu nx + nx)`` of the augmented
    problem for data ``x0``, ``W`` and ``law``."""
    x0, W = problem.check_data(x0, W)
    law = law.check(problem)
    ns, n = problem.n_scenarios, problem.horizon
    x0a = np.concatenate([x0, np.zeros((ns, problem.nu))], axis=1)
    data = np.concatenate([law.K.reshape(n, -1), law.r], axis=1)  # (N, nu nx + nx)
    Wa = np.concatenate([W, np.broadcast_to(data, (ns,) + data.shape)], axis=2)
    return x0a, np.ascontiguousarray(Wa)


def augmented_backoff(problem: ScenarioProblem, backoff: np.ndarray | None) -> np.ndarray | None:
    """The back-off ``(N, ng + 2 nu)`` of the augmented problem: the state constraints',
    none on the input rows."""
    b = problem.check_backoff(backoff)
    if b is None:
        return None
    return np.concatenate([b, np.zeros((problem.horizon, 2 * problem.nu))], axis=1)


class FeedbackScenarioSolver:
    """A registered solver on a feedback problem (``make_solver`` builds it; module docstring).

    The law of a solve (:meth:`solve`'s ``law``) is, when not given, the TV-LQR of
    :func:`~controllers.feedback_law.feedback_law` along a reference plan: ``u_guess`` when
    given, else the nominal inputs (:attr:`MPCSolution.nominal_u`) of this solver's last
    usable plan shifted by one step, else (first solve, after :meth:`reset` or after a
    solve without a usable plan) the plan of the same problem in open loop, solved first
    by the same solver (its time is part of ``solve_time``). The decision's warm start is
    the reference plan (clipped into the bounds).

    Args:
        problem: a problem with ``prediction="feedback"``.
        spec: the registry's record of the solver to run (:class:`SolverSpec`).
        **options: that solver's options (:func:`~controllers.solvers.make_solver`).
    """

    def __init__(self, problem: ScenarioProblem, spec: SolverSpec, **options: Any) -> None:
        if problem.prediction != "feedback":
            raise ValueError(
                f"FeedbackScenarioSolver: problem.prediction={problem.prediction!r}; must be "
                "'feedback'"
            )
        t0 = time.perf_counter()
        self.problem = problem
        self.spec = spec
        self.options = dict(options)
        self.augmented = augmented_problem(problem)
        self.inner: ScenarioSolver = spec.build(self.augmented, **options)
        self._open_loop: ScenarioSolver | None = None
        self._reference: np.ndarray | None = None  # nominal inputs of the last usable plan
        self._last_v: np.ndarray | None = None
        self.build_time = time.perf_counter() - t0  # [s]

    def open_loop_solver(self) -> ScenarioSolver:
        """The same solver on the open-loop problem (built at its first use)."""
        if self._open_loop is None:
            problem = dataclasses.replace(self.problem, prediction="open_loop")
            self._open_loop = self.spec.build(problem, **self.options)
        return self._open_loop

    def set_max_time(self, seconds: float) -> None:
        """The wall-clock limit [s] of the next solves of the inner solver and of the
        open-loop reference solve (for solvers that take one: ``set_max_time``)."""
        self.options["max_time"] = float(seconds)
        for solver in (self.inner, self._open_loop):
            if solver is not None and hasattr(solver, "set_max_time"):
                solver.set_max_time(seconds)

    def reset(self) -> None:
        """Forget the warm start and the reference plan."""
        self.inner.reset()
        if self._open_loop is not None:
            self._open_loop.reset()
        self._reference = self._last_v = None

    def solve(
        self,
        x0: np.ndarray,
        W: np.ndarray,
        u_guess: np.ndarray | None = None,
        backoff: np.ndarray | None = None,
        law: FeedbackLaw | None = None,
    ) -> MPCSolution:
        """The feedback plan for initial state(s) ``x0`` and latent forces ``W``.

        Args:
            x0: initial state(s) ``(nx,)`` or ``(Ns, nx)``, in the states' units.
            W: latent forces ``(Ns, N, nw)`` (or ``(Ns, N)``).
            u_guess: the reference plan ``(N, nu)`` (the law's linearisation and the
                decision's warm start); by default see the class docstring.
            backoff: constraint tightening of the state constraints, as for
                :meth:`ScenarioProblem.check_backoff`.
            law: the feedback law; ``None`` computes it (class docstring).

        Returns:
            ``u`` the decision ``v`` (``u[0]`` is applied); ``objective`` and ``slack`` the
            feedback problem's (state and input slacks: ``extra["state_slack"]``,
            ``extra["input_slack"]``); ``predicted`` ``(Ns, N+1, nx)`` the scenarios' states;
            ``law`` and ``nominal_u``; status, success, usable and iterations the inner
            solver's; ``extra`` the inner solver's, plus ``inputs`` ``(Ns, N, nu)`` (each
            scenario's inputs), ``reference`` (``"law"``, ``"u_guess"``,
            ``"previous_plan"`` or ``"open_loop_solve"``), ``open_loop`` (that solve's
            status, iterations and time [s], or ``None``) and ``gain_time`` [s].
        """
        t0 = time.perf_counter()
        p = self.problem
        x0, W = p.check_data(x0, W)
        b = p.check_backoff(backoff)
        law = p.check_law(law)
        open_loop, gain_time = None, 0.0
        ref, source = reference_plan(p, u_guess, self._reference)
        if law is None:
            if ref is None:
                guess = None if self._last_v is None else shifted(self._last_v)
                ol = self.open_loop_solver().solve(x0, W, u_guess=guess, backoff=b)
                open_loop = {
                    "status": ol.status,
                    "iterations": ol.iterations,
                    "solve_time": ol.solve_time,
                }
                ref, source = ol.u, "open_loop_solve"
            t1 = time.perf_counter()
            law = feedback_law(p, x0, W, ref)
            gain_time = time.perf_counter() - t1
        guess = None if ref is None else p.system.clip_input(ref)
        x0a, Wa = augmented_data(p, x0, W, law)
        with self._time_left(t0 if open_loop is not None else None):
            sol = self.inner.solve(x0a, Wa, u_guess=guess, backoff=augmented_backoff(p, b))
        return self._result(sol, x0, W, b, law, t0, source, open_loop, gain_time)

    @contextlib.contextmanager
    def _time_left(self, t0: float | None) -> Iterator[None]:
        """After an open-loop reference solve begun at ``t0``: the inner solve gets what is
        left of ``max_time`` (one limit for the whole step), where it takes a limit."""
        limit = float(self.options.get("max_time", math.inf))
        if t0 is None or not math.isfinite(limit) or not hasattr(self.inner, "set_max_time"):
            yield
            return
        self.inner.set_max_time(max(limit - (time.perf_counter() - t0), 1e-6))
        try:
            yield
        finally:
            self.inner.set_max_time(limit)

    def _result(
        self,
        sol: MPCSolution,
        x0: np.ndarray,
        W: np.ndarray,
        b: np.ndarray | None,
        law: FeedbackLaw,
        t0: float,
        source: str,
        open_loop: dict[str, Any] | None,
        gain_time: float,
    ) -> MPCSolution:
        """The inner solution mapped back to the feedback problem (see :meth:`solve`)."""
        p, nx = self.problem, self.problem.nx
        v = np.asarray(sol.u, dtype=float).reshape(p.horizon, p.nu)
        if sol.predicted is not None and np.all(np.isfinite(sol.predicted)):
            X = np.ascontiguousarray(sol.predicted[:, :, :nx])
            U = np.ascontiguousarray(sol.predicted[:, 1:, nx:])
        else:
            X, U = p.rollout(x0, W, v, law), p.inputs(x0, W, v, law)
        nominal = nominal_inputs(p, x0, W, v, law)
        self._last_v = v.copy()
        self._reference = nominal.copy() if sol.usable else None
        extra = dict(sol.extra or {})
        extra.update(
            inputs=U,
            state_slack=float(np.sum(p.minimal_slack(X, b))),
            input_slack=float(np.sum(p.input_slack(U))),
            reference=source,
            open_loop=open_loop,
            gain_time=gain_time,
        )
        return MPCSolution(
            u=v,
            objective=sol.objective,
            slack=sol.slack,
            status=sol.status,
            success=sol.success,
            solve_time=time.perf_counter() - t0,
            iterations=sol.iterations,
            predicted=X,
            extra=extra,
            usable=sol.usable,
            law=law,
            nominal_u=nominal,
        )


__all__ = [
    "ClosedLoopConstraints",
    "ClosedLoopRhs",
    "FeedbackScenarioSolver",
    "augmented_backoff",
    "augmented_data",
    "augmented_problem",
]
