"""The feedback prediction solved natively by the fast SQP (the Python loop).

On a problem with ``prediction="feedback"`` (:mod:`controllers.problem`) the fast SQP's
decision is the nominal inputs ``v`` ``(N, nu)``; scenario ``s`` applies
``u_{s,k} = v_k + K_k (x_{s,k} - r_k)`` (``K_0 = 0``) under the frozen law of the solve. The
condensed model (:class:`~controllers.solvers.fast.condensed.CondensedModel` with
``feedback``) evaluates everything on the closed-loop step:

* the sensitivities with ``A_k + B_k K_k`` (``A``, ``B`` at each scenario's own input);
* below each scenario's state sensitivities, those of its input (``K_k S_k + E_k``): the
  input rows ``u_{s,k} <= hi`` and ``lo <= u_{s,k}`` are one more row type of the screening
  and check-and-add, softened by one slack per (step, input, side) shared by the scenarios;
* the per-scenario input cost in the rollout, the gradient and the exact Hessian.

``v_0`` keeps the input bounds (it is applied now); ``v_k`` (``k >= 1``) is free
(``FastSolverOptions.feedback_bounds="first"``, the default) or bounded too (``"all"``: the
formulation of the exact rewrite in :mod:`controllers.solvers.feedback`, which the other
solvers run and the tests use as the oracle).

:class:`FeedbackMixin` chooses the law of a solve as the rewrite does: given (``law=``), or
the TV-LQR (:func:`~controllers.feedback_law.feedback_law`) along a reference plan: ``u_guess``,
else the nominal inputs of the last usable plan shifted by one step, else the plan of the
same problem in open loop. That open-loop reference is solved by the same condensed SQP with
the zero law and every ``v_k`` bounded, which is exactly the open-loop problem (each
scenario applies ``v``; the input rows repeat the bounds and are left out).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from controllers.feedback_law import (
    FeedbackLaw,
    feedback_law,
    nominal_inputs,
    reference_plan,
    shifted,
)
from controllers.problem import MPCSolution, ScenarioProblem, is_usable
from controllers.solvers.fast.condensed import CondensedModel
from controllers.solvers.fast.iterate import Rollout
from controllers.solvers.fast.options import FastSolverOptions

# The outcome of one run of the SQP with its extra starts:
# (the plan's rollout, status, success, iterations, extra).
Run = tuple[Rollout, str, bool, int, dict[str, Any]]


def applied_inputs(X: np.ndarray, v: np.ndarray, law: FeedbackLaw) -> np.ndarray:
    """The inputs ``(Ns, N, nu)`` the scenarios of states ``X`` ``(Ns, N+1, nx)`` apply under
    the decision ``v`` ``(N, nu)`` and ``law``."""
    U = v[None] + np.einsum("kij,skj->ski", law.K, X[:, :-1] - law.r[None])
    U[:, 0] = v[0]
    return U


class FeedbackMixin:
    """The feedback prediction of :class:`~controllers.solvers.fast.solver.FastScenarioSolver`
    (a base class of it; the module docstring)."""

    problem: ScenarioProblem
    options: FastSolverOptions
    condensed: CondensedModel
    _lower: np.ndarray
    _upper: np.ndarray

    def _run(self, x0: np.ndarray, W: np.ndarray, u0: np.ndarray, b, t_start: float) -> Run:
        raise NotImplementedError  # (the solver's)

    def _init_feedback(self) -> None:
        """The bounds of the two kinds of solve, and the memory of the last plans."""
        nu = self.problem.nu
        lower, upper = self.condensed.lower, self.condensed.upper
        free_lower, free_upper = lower.copy(), upper.copy()
        free_lower[nu:], free_upper[nu:] = -np.inf, np.inf
        self._phase_bounds = {"all": (lower, upper), "first": (free_lower, free_upper)}
        self._reference: np.ndarray | None = None  # nominal inputs of the last usable plan
        self._last_v: np.ndarray | None = None  # the last feedback decision
        self._last_open: np.ndarray | None = None  # the last open-loop reference plan

    def _reset_feedback(self) -> None:
        self._reference = self._last_v = self._last_open = None

    def _use_law(self, K: np.ndarray, r: np.ndarray, bounds: str) -> None:
        """Set the law of the next runs and the decision's bounds (``"first"`` or ``"all"``);
        a step's input rows count unless they repeat the hard bounds (``K_k = 0`` on a
        bounded ``v_k``)."""
        self._lower, self._upper = self._phase_bounds[bounds]
        bounded = np.arange(self.problem.horizon) == 0
        if bounds == "all":
            bounded[:] = True
        zero = ~np.any(K.reshape(K.shape[0], -1) != 0.0, axis=1)
        self.condensed.set_law(K, r, ~(bounded & zero))

    def _start(self, guess: np.ndarray | None, last: np.ndarray | None) -> np.ndarray:
        """The first iterate: ``guess``, else ``last`` shifted, else zeros, in the bounds."""
        p = self.problem
        if guess is None:
            guess = np.zeros((p.horizon, p.nu)) if last is None else shifted(last)
        return np.clip(np.asarray(guess, dtype=float).ravel(), self._lower, self._upper)

    def _reference_solve(
        self, x0: np.ndarray, W: np.ndarray, b: np.ndarray | None, t_start: float
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """The open-loop plan of the problem (the zero law, every ``v_k`` bounded), warm-started
        from the last one shifted, within the time limit of the solve that began at
        ``t_start``: ``(plan (N, nu), {status, iterations, solve_time})``."""
        p = self.problem
        t0 = time.perf_counter()
        self._use_law(np.zeros((p.horizon, p.nu, p.nx)), np.zeros((p.horizon, p.nx)), "all")
        start = self._start(None, self._last_open)
        ro, status, _, iterations, _ = self._run(x0, W, start, b, t_start)
        plan = ro.u.reshape(p.horizon, p.nu).copy()
        self._last_open = plan
        info = {"status": status, "iterations": iterations}
        return plan, {**info, "solve_time": time.perf_counter() - t0}

    def _feedback_solve(
        self,
        x0: np.ndarray,
        W: np.ndarray,
        u_guess: np.ndarray | None,
        backoff: np.ndarray | None,
        law: FeedbackLaw | None,
    ) -> MPCSolution:
        """:meth:`FastScenarioSolver.solve` on a feedback problem (arguments and result as
        :meth:`controllers.solvers.feedback.FeedbackScenarioSolver.solve`)."""
        t0 = time.perf_counter()
        p = self.problem
        x0, W = p.check_data(x0, W)
        b = p.check_backoff(backoff)
        law = p.check_law(law)
        reference, gain_time = None, 0.0
        ref, source = reference_plan(p, u_guess, self._reference)
        if law is None:
            if ref is None:
                ref, reference = self._reference_solve(x0, W, b, t0)
                source = "open_loop_solve"
            t1 = time.perf_counter()
            law = feedback_law(p, x0, W, ref)
            gain_time = time.perf_counter() - t1
        self._use_law(law.K, law.r, self.options.feedback_bounds)
        guess = None if ref is None else p.system.clip_input(ref)
        # (one time limit for the whole solve, the reference solve included)
        run = self._run(x0, W, self._start(guess, self._last_v), b, t0)
        info = {"reference": source, "open_loop": reference, "gain_time": gain_time}
        return self._feedback_result(run, x0, W, law, t0, info)

    def _feedback_result(
        self,
        run: Run,
        x0: np.ndarray,
        W: np.ndarray,
        law: FeedbackLaw,
        t0: float,
        info: dict[str, Any],
    ) -> MPCSolution:
        """The solution of a feedback run: the decision, the scenarios' states and inputs, the
        nominal inputs (the next reference when the plan is usable)."""
        ro, status, success, iterations, extra = run
        p = self.problem
        v = ro.u.reshape(p.horizon, p.nu).copy()
        X = np.ascontiguousarray(ro.X.transpose(2, 0, 1))
        nominal = nominal_inputs(p, x0, W, v, law)
        usable = is_usable(success, ro.merit, extra["start_merit"])
        self._last_v = v.copy()
        self._reference = nominal.copy() if usable else None
        rows = np.maximum(ro.G.max(axis=2), 0.0)
        extra.update(
            inputs=applied_inputs(X, v, law),
            state_slack=float(rows[: p.ng].sum()),
            input_slack=float(rows[p.ng :].sum()),
            **info,
        )
        return MPCSolution(
            u=v,
            objective=ro.merit,
            slack=ro.slack,
            status=status,
            success=success,
            solve_time=time.perf_counter() - t0,
            iterations=iterations,
            predicted=X,
            extra=extra,
            usable=usable,
            law=law,
            nominal_u=nominal,
        )


__all__ = ["FeedbackMixin", "applied_inputs"]
