"""Fast default solver of the scenario MPC problem: a condensed exact-Hessian SQP, for any model.

:class:`FastScenarioSolver` minimises exactly :meth:`ScenarioProblem.objective` (the
scenario-averaged quadratic cost plus the exact L1 penalty on the ``ng N`` shared slacks)
over the shared inputs ``u`` ``(N, nu)``, like the IPOPT reference
(:class:`controllers.solvers.casadi.ipopt.IpoptScenarioSolver`), but exploits the structure of
the problem. Everything it knows about the system comes from the system definition
(:class:`lfm_env.system.ControlSystem`) through
:class:`~controllers.solvers.fast.condensed.CondensedModel`:

* **Condensing.** The latent forces ``W`` do not depend on ``u``, so every scenario's
  states are explicit functions of the ``N nu`` inputs. Rollouts use the model's NumPy
  step on all scenarios at once; forward sensitivities and the adjoint sweep use step
  Jacobians and Hessians that CasADi generates from the same right-hand side, evaluated
  on all ``Ns N`` points per call.
* **Exact Hessian.** The Hessian of the Lagrangian with respect to ``u`` (second-order
  adjoint), including the curvature of the dynamics and of the constraints weighted by
  the QP multipliers. When it is indefinite, ``sigma J_A' J_A`` of the constraints
  predicted active is added (which leaves the QP step on that active set unchanged), and
  only if that fails are small eigenvalues raised to a floor.
* **Shared linear rows.** Constraints whose condensed Jacobian is one constant row per
  step for every scenario (found symbolically from the model; the bicycle's speed
  bounds) reduce exactly to the extreme scenario per step: one row each.
* **Screened scenario rows with check-and-add.** The other constraints' rows are limited
  to the few scenarios closest to the current maximum of each (constraint, step), plus
  the scenarios extreme in the states that constraint depends on. After each QP solve the
  linearisation of *every* scenario row is checked at the QP step; violated rows are added
  and the QP re-solved, so the accepted step is exactly the step of the full QP.
* **Exact penalty inside the QP.** One slack per (constraint, step), shared by its rows,
  as in the NLP; a dense QP whose rows keep their slots while they stay in it
  (:class:`~controllers.solvers.fast.qp.slot_qp.SlotQP`), solved by qpOASES with hot starts
  while it is small and by the project's interior point with the slacks eliminated
  (:mod:`~controllers.solvers.fast.qp.elastic_ipm`) when it is large (``qp_solver="auto"``).
* **Globalisation.** A box trust region on the QP step (a fraction of each input's
  range: shrunk to half the accepted step after backtracking or when the merit falls by
  less than a quarter of what the QP model predicted, doubled after a full step that
  reached it and did better; never below ``min_trust_radius``), inside a backtracking
  Armijo line search on the exact-penalty merit, with a second-order correction against
  the Maratos effect (for a full step that fails the search, or passes it far short of the
  model's promise while the slack grew). Where the Hessian had to be floored on negative
  curvature, the QP model is flat in those directions and only the trust region keeps the
  step from running to the input bounds. (``trust_radius=0``: Levenberg-Marquardt damping after
  heavy backtracking instead.) A full step whose merit decrease came close to the linear
  prediction is tried 2, 4, ... times as long while the merit keeps falling
  (``max_expand``): where the model is too curved, full steps otherwise shrink by a
  constant factor and the SQP crawls.
* **Extra starts.** The problem is not convex. A system may declare inputs whose sign
  flip mirrors a manoeuvre (``ControlSystem.mirror_inputs``, the bicycle's steering);
  when a plan uses them hard, the SQP also starts from the mirrored plan (and, with
  slack, from the plan with those inputs at zero), drops an extra start once its local
  model cannot beat the best plan or it heads for that same plan, and keeps the best.

The result is a KKT point of the full scenario problem: started from a local optimum that
IPOPT found, it stays there up to solver tolerances.

Where things are: the options in :mod:`controllers.solvers.fast.options`; one
iteration's subproblem (convexification, screening, check-and-add, the QP step) in
:mod:`controllers.solvers.fast.subproblem`; the extra starts' choices in
:mod:`controllers.solvers.fast.restarts`; the QP in :mod:`controllers.solvers.fast.qp.slot_qp`;
the derivatives in :mod:`controllers.solvers.fast.condensed` (and its C library,
:mod:`controllers.solvers.fast.codegen.build`); the line search, second-order correction, step
expansion and trust region in :mod:`controllers.solvers.fast.globalisation`; the SQP loop and
the extra starts here.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from controllers.feedback_law import FeedbackLaw
from controllers.problem import MPCSolution, ScenarioProblem, is_usable
from controllers.solvers.fast.closed_loop import FeedbackMixin, Run
from controllers.solvers.fast.condensed import CondensedModel
from controllers.solvers.fast.globalisation import Evaluate, GlobalisationMixin, ModelStep
from controllers.solvers.fast.iterate import Linearisation, Rollout
from controllers.solvers.fast.options import HESSIAN_MODIFICATIONS, RESTARTS, FastSolverOptions
from controllers.solvers.fast.qp.slot_qp import resolve_qp_solver
from controllers.solvers.fast.restarts import RestartMixin
from controllers.solvers.fast.subproblem import QP, QPStep, SubproblemMixin


class FastScenarioSolver(SubproblemMixin, GlobalisationMixin, RestartMixin, FeedbackMixin):
    """Condensed exact-Hessian SQP solver of any :class:`ScenarioProblem`.

    Same interface and result semantics as
    :class:`controllers.solvers.casadi.ipopt.IpoptScenarioSolver`: build once, call
    :meth:`solve` at every step; the previous solution shifted by one step is the default
    initial guess.

    Args:
        problem: the problem (its model's system gives every expression).
        **options: fields of :class:`FastSolverOptions` (e.g. ``max_iter=30``).

    Raises:
        ValueError: on an unknown or out-of-range option.
    """

    def __init__(self, problem: ScenarioProblem, **options: Any) -> None:
        unknown = set(options) - set(FastSolverOptions.__dataclass_fields__)
        if unknown:
            raise ValueError(f"unknown {type(self).__name__} options: {sorted(unknown)}")
        self.problem = problem
        self.options = FastSolverOptions(**options)
        self.condensed = m = CondensedModel(problem)
        m.threads = self.options.threads
        n = problem.horizon
        self._n_u = m.n_u
        self._lower, self._upper = m.lower, m.upper
        # Shared rows ordered (step, shared constraint).
        n_l = m.shared.size
        self._n_shared = n_l * n
        self._a_shared = m.shared_rows.transpose(1, 0, 2).reshape(n * n_l, m.n_u)
        self._n_groups = max(m.screened.size * n, 1)
        self._eye = np.eye(m.n_u)
        self._floor_eye = self._eye * self.options.hessian_floor
        self._qps: dict[tuple[int, int, bool], QP] = {}
        self._hard_solver = resolve_qp_solver(self.options.qp_solver, m.n_u, elastic=False)
        self._prev_u: np.ndarray | None = None
        self._deadline = math.inf  # time.perf_counter() value ending the current solve
        # (N nu,) each input's range; inf where it has none (an unbounded input gets no
        # trust region, a fixed one needs none)
        span = self._upper - self._lower
        self._range = np.where(np.isfinite(span) & (span > 0), span, np.inf)
        self._radius = 0.0  # current trust radius (fraction of the range; 0: none)
        self._hard_first = True  # the next QP is tried without slacks first
        # The last start's linearisation: its arrays (every entry rewritten) serve the next
        # start's first one, so large problems do not fault in fresh pages at every start.
        self._spare_lin: Linearisation | None = None
        # A list to record one dict per SQP iteration into (diagnostics), or None.
        self.trace: list[dict[str, Any]] | None = None
        if m.feedback:  # (the decision's bounds then depend on the kind of solve)
            self._init_feedback()

    @property
    def backend(self) -> str:
        """How the derivatives are evaluated: :attr:`CondensedModel.backend`."""
        return self.condensed.backend

    # ------------------------------------------------------------------ public API

    def reset(self) -> None:
        """Forget the warm start: the next solve starts from zero inputs (with feedback,
        also the reference plan)."""
        self._prev_u = None
        self._hard_first = True
        if self.condensed.feedback:
            self._reset_feedback()

    def set_max_time(self, seconds: float) -> None:
        """The wall-clock limit of the next solves [s] (``FastSolverOptions.max_time``;
        an agent with a deadline sets it at every step)."""
        if seconds != self.options.max_time:
            self.options = dataclasses.replace(self.options, max_time=float(seconds))

    def __getstate__(self) -> dict[str, Any]:
        # The QP objects hold raw buffers of a CasADi function, the model generated code:
        # rebuild them after unpickling (e.g. in a worker process).
        state = self.__dict__.copy()
        state["_qps"] = {}
        state["condensed"] = None
        state["_spare_lin"] = None
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self.condensed = CondensedModel(self.problem)
        self.condensed.threads = self.options.threads

    def solve(
        self,
        x0: np.ndarray,
        W: np.ndarray,
        u_guess: np.ndarray | None = None,
        backoff: np.ndarray | None = None,
        law: FeedbackLaw | None = None,
        iterations: int | None = None,
    ) -> MPCSolution:
        """Solve the scenario problem for initial state(s) ``x0`` and latent forces ``W``.

        Args:
            x0: initial state ``(nx,)`` or ``(Ns, nx)``, in the states' units.
            W: latent forces ``(Ns, N, nw)`` (or ``(Ns, N)`` for one component).
            u_guess: initial input sequence ``(N, nu)``; by default the previous solution
                shifted by one step (zeros clipped into the bounds on the first solve).
                With feedback: the reference plan (the law's linearisation and the
                decision's warm start; :mod:`controllers.solvers.fast.closed_loop`).
            backoff: constraint tightening ``(N, ng)`` or ``(ng,)``, ``>= 0``
                (:meth:`ScenarioProblem.check_backoff`); ``None`` for none.
            law: a feedback problem's law (``None``: from the reference plan); an open-loop
                problem takes none.
            iterations: at most this many SQP iterations and no extra starts in this call
                (a real-time iteration: ``iterations=1``; with feedback it bounds the
                open-loop reference solve too); ``None``: the options' ``max_iter``.

        Returns:
            The solution: ``u`` inside the input bounds; ``objective``, ``slack`` and
            ``predicted`` those of :class:`ScenarioProblem` (``objective``,
            ``minimal_slack`` summed, ``rollout``) for ``u``, computed by the solver's own
            vectorised rollout (equal up to rounding); ``solve_time`` the wall time of the
            whole call; ``extra`` counts QP solves (``qp_solves``; of them without
            slacks ``qp_hard``, and hard QPs rejected for the QP with slacks
            ``qp_hard_rejected``: see ``FastSolverOptions.elastic_qp``), the most QP rows
            (``qp_rows``), QP calls retried after a failure (``qp_retries``), iterations
            whose check-and-add rounds ran out (``qp_rounds_exhausted``), merit
            evaluations and second-order corrections, names the derivative backend
            (``backend``), the C library's threads (``threads``: 1 without
            OpenMP, whatever was asked) and its loops' vectorisation
            (``vector_math``: ``CondensedModel.vector_math``), the QP solver option
            (``qp_solver``) with the QP calls per solver it resolved to (``qp_calls``, e.g.
            ``{"qpoases": 12}``), gives the first start's ``{"status", "iterations"}``
            (``first_start``), and ``extra["restarts"]`` maps each extra start tried to
            ``"kept"`` or the status it ended with; ``iterations`` counts the iterations of
            every start; ``extra["start_merit"]`` is the warm start's merit. A solve
            that does not converge does not raise: it returns the best iterate (the merit
            decreases monotonically) with ``success=False``, and ``usable=True`` when that
            iterate lies below the warm start (at least one accepted step). A start whose
            merit stagnates (``acceptable_iter`` steps in a row, each lowering it by at most
            ``acceptable_tol`` of it) ends with status ``"Solved_To_Acceptable_Level"``, a
            success.

        Extra starts: when the first plan drives an input of ``system.mirror_inputs``
        beyond ``restart_threshold`` of its bound, the SQP also starts from that plan with
        those inputs negated (``"mirror"``) and, if the plan needs slack, with them at zero
        (``"straight"``). After ``restart_probe`` iterations an extra start is abandoned as
        soon as its merit plus ``restart_optimism`` times the decrease its local model
        predicts still lies above the best plan so far; the plan with the lowest objective
        is returned (a failed start never replaces a successful one); an extra start that
        comes within ``restart_same_tol`` of the best plan is stopped too, and so is one
        within ``restart_near_tol`` that is still worse than it and drawing closer.

        With feedback the result is :meth:`FeedbackScenarioSolver.solve`'s (``u`` the
        decision ``v``; ``law``, ``nominal_u``; ``extra["inputs"]``, ``"state_slack"``,
        ``"input_slack"``, ``"reference"``, ``"open_loop"``, ``"gain_time"``).

        Raises:
            ValueError: on wrongly shaped or non-finite ``x0``, ``W`` or ``u_guess``, or a
                law for an open-loop problem.
        """
        with self._limited(iterations):
            if self.condensed.feedback:
                return self._feedback_solve(x0, W, u_guess, backoff, law)
            return self._open_loop_solve(x0, W, u_guess, backoff, law)

    @contextlib.contextmanager
    def _limited(self, iterations: int | None) -> Iterator[None]:
        """Within it, the options of a solve limited to ``iterations`` SQP iterations without
        extra starts (``None``: the options as they are)."""
        saved = self.options
        self.options = saved.limited(iterations)
        try:
            yield
        finally:
            self.options = saved

    def _open_loop_solve(
        self,
        x0: np.ndarray,
        W: np.ndarray,
        u_guess: np.ndarray | None,
        backoff: np.ndarray | None,
        law: FeedbackLaw | None,
    ) -> MPCSolution:
        """:meth:`solve` of an open-loop problem."""
        t_start = time.perf_counter()
        problem, n, nu = self.problem, self.problem.horizon, self.problem.nu
        problem.check_law(law)  # (refuses a law: this problem is open loop)
        x0, W = problem.check_data(x0, W)
        b = problem.check_backoff(backoff)
        if u_guess is not None:
            u0 = problem.check_inputs(u_guess, "u_guess").ravel()
        elif self._prev_u is not None:
            u0 = np.concatenate([self._prev_u[1:], self._prev_u[-1:]]).ravel()
        else:
            u0 = np.zeros(n * nu)
        u0 = np.clip(u0, self._lower, self._upper)
        ro, status, success, iterations, extra = self._run(x0, W, u0, b, t_start)

        u = ro.u.reshape(n, nu).copy()
        self._prev_u = u.copy()
        return MPCSolution(
            u=u,
            objective=ro.merit,
            slack=ro.slack,
            status=status,
            success=success,
            solve_time=time.perf_counter() - t_start,
            iterations=iterations,
            predicted=np.ascontiguousarray(ro.X.transpose(2, 0, 1)),
            extra=extra,
            usable=is_usable(success, ro.merit, extra["start_merit"]),
        )

    def _run(
        self, x0: np.ndarray, W: np.ndarray, u0: np.ndarray, b: np.ndarray | None, t_start: float
    ) -> Run:
        """The SQP from ``u0`` (inside the bounds) and its extra starts on the checked data,
        with the time limit counted from ``t_start``: the best start's ``(rollout, status,
        success, iterations, extra)``."""
        data = _Data(
            x0T=np.ascontiguousarray(x0.T),
            W=np.ascontiguousarray(W.transpose(1, 0, 2)),
            W_lanes=np.ascontiguousarray(W.transpose(2, 1, 0)),
            cost0=self.condensed.state_cost0(x0),
            backoff=None if b is None else np.ascontiguousarray(b.T[:, :, None]),
        )
        deadline = t_start + self.options.max_time
        for qp in self._qps.values():  # no hot start carries over from another problem
            qp.reset()
        ro, status, success, iterations, extra = self._sqp(data, u0, deadline=deadline)
        first_status, first_iterations = status, iterations
        extra["restarts"] = {}
        for name in self._restart_names(ro):
            if time.perf_counter() >= deadline:
                extra["restarts"][name] = "no_time"
                continue
            # The problem is not convex: try another start, abandon it once it cannot
            # plausibly beat the best plan so far, and keep the better plan.
            u_alt = self._restart_guess(name, ro.u)
            bar = ro.merit + self.options.restart_margin * abs(ro.merit)
            ro2, status2, success2, iterations2, extra2 = self._sqp(
                data, u_alt, bar, ro.u, deadline=deadline
            )
            iterations += iterations2
            for key in (
                "qp_solves",
                "qp_hard",
                "qp_hard_rejected",
                "qp_retries",
                "qp_rounds_exhausted",
                "soc_steps",
                "merit_evals",
            ):
                extra[key] += extra2[key]
            extra["qp_rows"] = max(extra["qp_rows"], extra2["qp_rows"])
            for key, count in extra2["qp_calls"].items():
                extra["qp_calls"][key] = extra["qp_calls"].get(key, 0) + count
            better = ro2.merit < ro.merit - 1e-12 * (1.0 + abs(ro.merit))
            keep = better and (success2 or not success)
            extra["restarts"][name] = "kept" if keep else status2.lower()
            if keep:
                ro, status, success = ro2, status2, success2
        extra["backend"] = self.backend
        extra["threads"] = self.condensed.threads if self.condensed.openmp else 1
        extra["vector_math"] = getattr(self.condensed, "vector_math", 0)
        extra["qp_solver"] = self.options.qp_solver
        extra["first_start"] = {"status": first_status, "iterations": first_iterations}
        return ro, status, success, iterations, extra

    # ------------------------------------------------------------------ SQP

    def _check_time(self) -> None:
        """Raise :class:`_OutOfTime` once the current solve's deadline has passed."""
        if time.perf_counter() >= self._deadline:
            raise _OutOfTime

    def _sqp(
        self,
        data: _Data,
        u0: np.ndarray,
        abandon_above: float = math.inf,
        rival: np.ndarray | None = None,
        deadline: float = math.inf,
    ) -> tuple[Rollout, str, bool, int, dict[str, Any]]:
        """SQP iterations from ``u0``: ``(final rollout, status, success, iterations, extra)``.

        ``abandon_above``: after ``restart_probe`` iterations, stop with status
        ``"Abandoned"`` when the merit plus ``restart_optimism`` times the directional
        derivative along the QP step (the local model's promise) is above this value.
        ``rival``: the best plan so far; stop with status ``"Duplicate"`` when an iterate
        comes within ``restart_same_tol`` of it (the same local optimum again), or within
        ``restart_near_tol`` while still worse and closer than before (:meth:`_bound_for`).
        ``deadline``: a ``time.perf_counter()`` value; once past it, stop before the next
        QP solve or line-search trial with status ``"Maximum_WallTime_Exceeded"`` (not a
        success) and the last accepted iterate.
        """
        p, opt, condensed = self.problem, self.options, self.condensed
        stats: dict[str, Any] = {
            "qp_solves": 0,
            "qp_hard": 0,
            "qp_hard_rejected": 0,
            "qp_rows": 0,
            "qp_retries": 0,
            "qp_rounds_exhausted": 0,
            "soc_steps": 0,
            "merit_evals": 1,
            "qp_calls": {},
        }

        def evaluate(u: np.ndarray) -> Rollout:
            with np.errstate(all="ignore"):
                return condensed.evaluate(data.x0T, data.W, u, data.cost0, data.backoff)

        ro = evaluate(u0)
        stats["start_merit"] = ro.merit  # the warm start's (MPCSolution.usable)
        stats["start_slack"] = ro.slack
        if not math.isfinite(ro.merit):
            return ro, "Invalid_Initial_Point", False, 0, stats
        start = _Start(
            ro=ro,
            evaluate=evaluate,
            stats=stats,
            mu=np.zeros((condensed.n_rows, p.horizon, data.x0T.shape[1])),
            lin=self._spare_lin,  # the last linearisation (its arrays are reused)
        )
        status, success, iterations = "Maximum_Iterations_Exceeded", False, 0
        self._radius = opt.trust_radius
        self._deadline = deadline
        if opt.elastic_qp != "carried":  # (carried: as the last QP of the last solve left it)
            self._hard_first = opt.elastic_qp == "on_demand"
        self._spare_lin = None
        try:
            while iterations < opt.max_iter:
                if time.perf_counter() >= deadline:
                    status = "Maximum_WallTime_Exceeded"
                    break
                iterations += 1
                end = self._iteration(start, data, iterations, abandon_above, rival)
                if end is not None:
                    status, success = end
                    break
        except _OutOfTime:  # inside an iteration: keep the last accepted iterate
            status, success = "Maximum_WallTime_Exceeded", False
        self._spare_lin = start.lin
        return start.ro, status, success, iterations, stats

    def _iteration(
        self,
        start: _Start,
        data: _Data,
        iteration: int,
        abandon_above: float,
        rival: np.ndarray | None,
    ) -> tuple[str, bool] | None:
        """SQP iteration number ``iteration`` of ``start`` (see :meth:`_sqp`): the QP step, the
        tests that end the start before the line search, the line search, and the accepted
        step's own tests. Returns ``(status, success)`` when the start ends, else ``None``."""
        qp_step, failure = self._qp_step(start, data)
        if qp_step is None:
            return failure, False
        step = self._measure(start.ro, start.lin, qp_step)
        end = self._stop_before_search(start, step, iteration, abandon_above)
        if end is not None:
            return end
        accepted, t = self._line_search(
            start.evaluate, start.ro, start.lin, step, start.prev_step, start.stats
        )
        return self._accept(start, step, accepted, t, abandon_above, rival)

    def _qp_step(self, start: _Start, data: _Data) -> tuple[QPStep | None, str]:
        """The linearisation and Hessian at ``start.ro`` and the QP step from them, with the
        multipliers and the hard-active rows of that QP kept in ``start`` for the next
        convexification; ``(None, status)`` when the derivatives or the QP fail."""
        opt, condensed, ro = self.options, self.condensed, start.ro
        with np.errstate(all="ignore"):
            start.lin = lin = condensed.linearise(ro, data.W_lanes, recycle=start.lin)
            H = condensed.hessian(lin, start.mu, data.W_lanes)
        if not (np.isfinite(H).all() and np.isfinite(lin.grad).all()):
            return None, "Invalid_Derivatives"
        try:
            qp_step, start.mu = self._newton_step(
                lin, H, ro.u, start.active_pos, start.active_shared, start.damping, start.stats
            )
        except np.linalg.LinAlgError:  # eigen-decomposition failed: keep the best iterate
            return None, "Numerical_Error"
        if qp_step is None:
            return None, "QP_Failed"
        pos, mu = qp_step.pos, start.mu
        # Slack needed now: likely next time too (e.g. a problem infeasible for every
        # input), so the next QP gets its slacks at once.
        on_demand = opt.elastic_qp != "always"
        self._hard_first = on_demand and qp_step.slack_sum <= opt.add_tol
        # Hard-active constraints of this QP: the prediction for the next convexification.
        hard = (mu[pos[:, 0], pos[:, 1], pos[:, 2]] > 1e-9) & (
            qp_step.s_pos[pos[:, 0], pos[:, 1]] <= 1e-9
        )
        start.active_pos = pos[hard]
        shared_hard = (qp_step.lam_shared > 1e-9) & (qp_step.s_shared <= 1e-9)
        start.active_shared = np.nonzero(shared_hard)[0]
        return qp_step, ""

    def _stop_before_search(
        self, start: _Start, step: ModelStep, iteration: int, abandon_above: float
    ) -> tuple[str, bool] | None:
        """``(status, success)`` when the QP step ends the start before any line search: a
        negligible step or promise (converged), or an extra start that cannot win."""
        opt, ro, D = self.options, start.ro, step.D
        if np.max(np.abs(step.qp.d)) <= opt.step_tol:
            return "Solve_Succeeded", True
        if -D <= opt.tol * (1.0 + abs(ro.merit)) and not step.cut:
            # The QP step (not cut by the trust region) promises nothing beyond
            # rounding: a KKT point up to the tolerance.
            return "Solve_Succeeded", True
        if iteration >= opt.restart_probe and ro.merit + opt.restart_optimism * D > abandon_above:
            # Even a multiple of the decrease the local model promises leaves this
            # start above the plan to beat: give it up.
            return "Abandoned", False
        return None

    def _accept(
        self,
        start: _Start,
        step: ModelStep,
        accepted: Rollout | None,
        t: float,
        abandon_above: float,
        rival: np.ndarray | None,
    ) -> tuple[str, bool] | None:
        """Move ``start`` to the line search's ``accepted`` rollout (step length ``t``) and
        adapt the trust region; ``(status, success)`` when that ends the start (no
        acceptable point, stagnation, the rival plan again, convergence), else ``None``."""
        opt, ro, D = self.options, start.ro, step.D
        if accepted is None:
            # No decrease along a descent direction: converged up to rounding if the
            # predicted decrease is negligible, else a genuine failure.
            if -D <= 1e3 * opt.tol * (1.0 + abs(ro.merit)):
                return "Solve_Succeeded", True
            return "Line_Search_Failed", False
        u = ro.u
        size = float(np.max(np.abs(accepted.u - u)))
        if self.trace is not None:
            self.trace.append(self._trace_row(start, step, accepted, t, size))
        slack_change = abs(accepted.slack - ro.slack)
        prev_merit = ro.merit
        start.ro = ro = accepted
        # Stagnation (see FastSolverOptions.acceptable_tol): the merit has fallen by
        # next to nothing in each of the last acceptable_iter iterations.
        small = prev_merit - ro.merit <= opt.acceptable_tol * (1.0 + abs(ro.merit))
        start.acceptable = start.acceptable + 1 if small else 0
        if start.acceptable >= opt.acceptable_iter:
            return "Solved_To_Acceptable_Level", True
        if rival is not None and self._bound_for(rival, u, ro, abandon_above):
            return "Duplicate", False
        at_radius, start.damping = self._adapt_region(step, t, prev_merit, ro.merit, start.damping)
        ratio = size / start.prev_step if math.isfinite(start.prev_step) else 1.0
        # (a step cut by the trust region says nothing about convergence)
        predicted_next = size * min(ratio, 1.0) if t == 1.0 and not at_radius else math.inf
        start.prev_step = size if t == 1.0 else math.inf
        if predicted_next <= opt.final_step_tol and (
            ro.slack <= opt.add_tol or slack_change <= opt.add_tol * (1.0 + ro.slack)
        ):
            return "Solve_Succeeded", True
        return None

    def _trace_row(
        self, start: _Start, step: ModelStep, accepted: Rollout, t: float, size: float
    ) -> dict[str, Any]:
        """The diagnostics of one accepted iteration (:attr:`trace`)."""
        ro, D = start.ro, step.D
        return {
            "merit": ro.merit,
            "ratio": (accepted.merit - ro.merit) / D,
            "slack": ro.slack,
            "D": D,
            "t": t,
            "step": size,
            "d": float(np.max(np.abs(step.qp.d))),
            "damping": start.damping,
            "qp_solves": start.stats["qp_solves"],
            "rows": step.qp.pos.shape[0],
            "eig0": self._last_eig[0],
            "eig1": self._last_eig[1],
            "sigma": self._last_sigma,
            "radius": self._radius,
        }


class _OutOfTime(Exception):
    """The solve's wall-clock limit (``max_time``) passed inside an SQP iteration."""


@dataclass
class _Data:
    """The data of one solve, in the layouts the condensed model works on."""

    x0T: np.ndarray  # (nx, Ns) initial states, component-major
    W: np.ndarray  # (N, Ns, nw) forces per step
    W_lanes: np.ndarray  # (nw, N, Ns) forces as evaluation points
    cost0: float  # averaged stage cost of the initial states (a constant)
    backoff: np.ndarray | None = None  # (ng, N, 1) constraint tightening, or None


@dataclass
class _Start:
    """One SQP start between its iterations (:meth:`FastScenarioSolver._sqp`)."""

    ro: Rollout  # the current iterate
    evaluate: Evaluate  # the rollout and merit of inputs (N nu,)
    stats: dict[str, Any]  # the counts the solve reports in extra
    mu: np.ndarray  # (ng, N, Ns) the scenario rows' multipliers of the last QP
    lin: Linearisation | None  # the last linearisation (its arrays are reused)
    # The hard-active scenario rows (r, 3) and shared rows of the last QP: the prediction
    # for the next convexification.
    active_pos: np.ndarray = field(default_factory=lambda: np.empty((0, 3), dtype=int))
    active_shared: np.ndarray = field(default_factory=lambda: np.empty(0, dtype=int))
    prev_step: float = math.inf  # size of the last accepted full step
    acceptable: int = 0  # accepted steps in a row that each lowered the merit <= acceptable_tol
    damping: float = 0.0  # Levenberg-Marquardt term: grows while the quadratic model is poor


__all__ = ["HESSIAN_MODIFICATIONS", "RESTARTS", "FastScenarioSolver", "FastSolverOptions"]
