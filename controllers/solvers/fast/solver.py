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
:mod:`controllers.solvers.fast.codegen.build`); the SQP loop, line search, trust region and extra
starts here.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from controllers.problem import MPCSolution, ScenarioProblem
from controllers.solvers.fast.condensed import CondensedModel, Linearisation, Rollout
from controllers.solvers.fast.options import HESSIAN_MODIFICATIONS, RESTARTS, FastSolverOptions
from controllers.solvers.fast.restarts import RestartMixin
from controllers.solvers.fast.subproblem import QP, QPStep, SubproblemMixin
from controllers.solvers.fast.qp.slot_qp import resolve_qp_solver


class FastScenarioSolver(SubproblemMixin, RestartMixin):
    """Condensed exact-Hessian SQP solver of any :class:`ScenarioProblem`.

    Same interface and result semantics as :class:`controllers.solvers.casadi.ipopt.IpoptScenarioSolver`:
    build once, call :meth:`solve` at every step; the previous solution shifted by one
    step is the default initial guess.

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
        self.model = m = CondensedModel(problem)
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
        self._hard_first = False  # the next QP is tried without slacks first
        # The last start's linearisation: its arrays (every entry rewritten) serve the next
        # start's first one, so large problems do not fault in fresh pages at every start.
        self._spare_lin: Linearisation | None = None
        # A list to record one dict per SQP iteration into (diagnostics), or None.
        self.trace: list[dict[str, Any]] | None = None

    @property
    def backend(self) -> str:
        """How the derivatives are evaluated: :attr:`CondensedModel.backend`."""
        return self.model.backend

    # ------------------------------------------------------------------ public API

    def reset(self) -> None:
        """Forget the warm start: the next solve starts from zero inputs."""
        self._prev_u = None

    def __getstate__(self) -> dict[str, Any]:
        # The QP objects hold raw buffers of a CasADi function, the model generated code:
        # rebuild them after unpickling (e.g. in a worker process).
        state = self.__dict__.copy()
        state["_qps"] = {}
        state["model"] = None
        state["_spare_lin"] = None
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self.model = CondensedModel(self.problem)
        self.model.threads = self.options.threads

    def solve(
        self,
        x0: np.ndarray,
        W: np.ndarray,
        u_guess: np.ndarray | None = None,
        backoff: np.ndarray | None = None,
    ) -> MPCSolution:
        """Solve the scenario problem for initial state(s) ``x0`` and latent forces ``W``.

        Args:
            x0: initial state ``(nx,)`` or ``(Ns, nx)``, in the states' units.
            W: latent forces ``(Ns, N, nw)`` (or ``(Ns, N)`` for one component).
            u_guess: initial input sequence ``(N, nu)``; by default the previous solution
                shifted by one step (zeros clipped into the bounds on the first solve).
            backoff: constraint tightening ``(N, ng)`` or ``(ng,)``, ``>= 0``
                (:meth:`ScenarioProblem.check_backoff`); ``None`` for none.

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
            every start. A solve
            that does not converge does not raise: it returns the best iterate (the merit
            decreases monotonically) with ``success=False``. A start whose merit stagnates
            (``acceptable_iter`` steps in a row, each lowering it by at most
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

        Raises:
            ValueError: on wrongly shaped or non-finite ``x0``, ``W`` or ``u_guess``.
        """
        t_start = time.perf_counter()
        problem, n, nu = self.problem, self.problem.horizon, self.problem.nu
        x0, W = problem.check_data(x0, W)
        b = problem.check_backoff(backoff)
        if u_guess is not None:
            u0 = problem.check_inputs(u_guess, "u_guess").ravel()
        elif self._prev_u is not None:
            u0 = np.concatenate([self._prev_u[1:], self._prev_u[-1:]]).ravel()
        else:
            u0 = np.zeros(n * nu)
        u0 = np.clip(u0, self._lower, self._upper)

        data = _Data(
            x0T=np.ascontiguousarray(x0.T),
            W=np.ascontiguousarray(W.transpose(1, 0, 2)),
            W_lanes=np.ascontiguousarray(W.transpose(2, 1, 0)),
            cost0=self.model.state_cost0(x0),
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
        extra["threads"] = self.model.threads if self.model.openmp else 1
        extra["vector_math"] = getattr(self.model, "vector_math", 0)
        extra["qp_solver"] = self.options.qp_solver
        extra["first_start"] = {"status": first_status, "iterations": first_iterations}

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
        )

    # ------------------------------------------------------------------ SQP

    def _expand(
        self, evaluate: Any, u: np.ndarray, d: np.ndarray, accepted: Rollout, stats: dict
    ) -> tuple[Rollout, float]:
        """The best of ``u + t d`` for ``t = 1, 2, 4, ...`` while the merit keeps falling."""
        t = 1.0
        for _ in range(self.options.max_expand):
            self._check_time()
            u_try = np.clip(u + 2.0 * t * d, self._lower, self._upper)
            if np.array_equal(u_try, accepted.u):  # the bounds stop the step
                break
            trial = evaluate(u_try)
            stats["merit_evals"] += 1
            if not trial.merit < accepted.merit:
                break
            accepted, t = trial, 2.0 * t
        return accepted, t

    def _corrected(
        self,
        evaluate: Any,
        lin: Linearisation,
        qp_step: QPStep,
        u: np.ndarray,
        trial: Rollout,
        stats: dict,
    ) -> Rollout | None:
        """The second-order correction of the full step that gave ``trial`` (or None).

        The constraints' curvature made the full step infeasible: the QP's scenario rows
        are shifted by their second-order error at ``trial`` and the QP re-solved (against
        the Maratos effect); returns the rollout of the corrected step. (When the step came
        from the QP without slacks, so does the correction, without the multiplier test: it
        is a candidate like any other, kept by the caller only if the merit falls.)
        """
        pos, d = qp_step.pos, qp_step.d
        a_pos, _ = self.model.rows(lin, pos)
        g_try = trial.G[pos[:, 0], pos[:, 1], pos[:, 2]]
        qp_step.qp.set_position_bounds(qp_step.row, g_try - a_pos @ d)
        z_soc, _, ok_soc = qp_step.qp.solve()
        self._count(stats, qp_step.qp)
        if not ok_soc:
            return None
        stats["merit_evals"] += 1
        return evaluate(np.clip(u + z_soc[: self._n_u], self._lower, self._upper))

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
        p, opt, model = self.problem, self.options, self.model
        rho = p.slack_penalty
        ns = data.x0T.shape[1]
        mu = np.zeros((p.ng, p.horizon, ns))
        active_pos = np.empty((0, 3), dtype=int)
        active_shared = np.empty(0, dtype=int)
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
                return model.evaluate(data.x0T, data.W, u, data.cost0, data.backoff)

        ro = evaluate(u0)
        if not math.isfinite(ro.merit):
            return ro, "Invalid_Initial_Point", False, 0, stats
        status, success, iterations = "Maximum_Iterations_Exceeded", False, 0
        prev_step = math.inf  # size of the last accepted full step
        acceptable = 0  # accepted steps in a row that each lowered the merit <= acceptable_tol
        damping = 0.0  # Levenberg-Marquardt term: grows while the quadratic model is poor
        self._radius = opt.trust_radius
        self._deadline = deadline
        on_demand = opt.elastic_qp == "on_demand"
        self._hard_first = on_demand
        lin = self._spare_lin  # the last linearisation (its arrays are reused)
        self._spare_lin = None
        try:
            while iterations < opt.max_iter:
                if time.perf_counter() >= deadline:
                    status = "Maximum_WallTime_Exceeded"
                    break
                iterations += 1
                u = ro.u
                with np.errstate(all="ignore"):
                    lin = model.linearise(ro, data.W_lanes, recycle=lin)
                    H = model.hessian(lin, mu, data.W_lanes)
                if not (np.isfinite(H).all() and np.isfinite(lin.grad).all()):
                    status = "Invalid_Derivatives"
                    break
                try:
                    qp_step, mu = self._newton_step(
                        lin, H, u, active_pos, active_shared, damping, stats
                    )
                except np.linalg.LinAlgError:  # eigen-decomposition failed: keep the best iterate
                    status = "Numerical_Error"
                    break
                if qp_step is None:
                    status = "QP_Failed"
                    break
                d, pos = qp_step.d, qp_step.pos
                # Slack needed now: likely next time too (e.g. a problem infeasible for every
                # input), so the next QP gets its slacks at once.
                self._hard_first = on_demand and qp_step.slack_sum <= opt.add_tol
                # Hard-active constraints of this QP: the prediction for the next convexification.
                hard = (mu[pos[:, 0], pos[:, 1], pos[:, 2]] > 1e-9) & (
                    qp_step.s_pos[pos[:, 0], pos[:, 1]] <= 1e-9
                )
                active_pos = pos[hard]
                active_shared = np.nonzero(
                    (qp_step.lam_shared > 1e-9) & (qp_step.s_shared <= 1e-9)
                )[0]
                if np.max(np.abs(d)) <= opt.step_tol:
                    status, success = "Solve_Succeeded", True
                    break
                # Upper bound of the merit's directional derivative along d (< 0 unless d = 0).
                D = float(lin.grad @ d) + rho * (qp_step.slack_sum - ro.slack)
                predicted = -(D + 0.5 * qp_step.curvature)  # the QP model's merit decrease
                cut = opt.trust_radius > 0.0 and bool(
                    np.max(np.abs(d) / self._range) >= 0.99 * self._radius
                )
                if -D <= opt.tol * (1.0 + abs(ro.merit)) and not cut:
                    # The QP step (not cut by the trust region) promises nothing beyond
                    # rounding: a KKT point up to the tolerance.
                    status, success = "Solve_Succeeded", True
                    break
                if (
                    iterations >= opt.restart_probe
                    and ro.merit + opt.restart_optimism * D > abandon_above
                ):
                    # Even a multiple of the decrease the local model promises leaves this
                    # start above the plan to beat: give it up.
                    status = "Abandoned"
                    break

                # --- line search on the exact-penalty merit, with second-order correction ---
                soc_ok = opt.second_order_correction and pos.shape[0] > 0
                t = 1.0
                accepted = None
                while t >= opt.min_step:
                    self._check_time()
                    trial = evaluate(np.clip(u + t * d, self._lower, self._upper))
                    stats["merit_evals"] += 1
                    if trial.merit <= ro.merit + opt.armijo * t * D:
                        accepted = trial
                        if (
                            t == 1.0
                            and soc_ok
                            and opt.soc_below_ratio > 0.0
                            and trial.slack > ro.slack
                            and ro.merit - trial.merit < opt.soc_below_ratio * predicted
                        ):
                            # Accepted, but far below the model's promise while the slack
                            # grew: the same curvature error; keep the correction if better.
                            soc = self._corrected(evaluate, lin, qp_step, u, trial, stats)
                            if soc is not None and soc.merit < trial.merit:
                                stats["soc_steps"] += 1
                                accepted = soc
                        break
                    if t == 1.0 and soc_ok and trial.slack > ro.slack:
                        soc = self._corrected(evaluate, lin, qp_step, u, trial, stats)
                        if soc is not None and soc.merit <= ro.merit + opt.armijo * D:
                            stats["soc_steps"] += 1
                            accepted = soc
                            break
                    t *= opt.backtrack
                if (
                    accepted is not None
                    and t == 1.0
                    and opt.max_expand > 0
                    and ro.merit - accepted.merit >= -opt.expand_ratio * D
                    # no fast local convergence under way: the last step was cut, or this
                    # QP step is not less than half the last full step
                    and (not math.isfinite(prev_step) or float(np.max(np.abs(d))) > 0.5 * prev_step)
                ):
                    accepted, t = self._expand(evaluate, u, d, accepted, stats)
                if accepted is None:
                    # No decrease along a descent direction: converged up to rounding if the
                    # predicted decrease is negligible, else a genuine failure.
                    if -D <= 1e3 * opt.tol * (1.0 + abs(ro.merit)):
                        status, success = "Solve_Succeeded", True
                    else:
                        status = "Line_Search_Failed"
                    break
                step = float(np.max(np.abs(accepted.u - u)))
                if self.trace is not None:
                    self.trace.append(
                        {
                            "merit": ro.merit,
                            "ratio": (accepted.merit - ro.merit) / D,
                            "slack": ro.slack,
                            "D": D,
                            "t": t,
                            "step": step,
                            "d": float(np.max(np.abs(d))),
                            "damping": damping,
                            "qp_solves": stats["qp_solves"],
                            "rows": pos.shape[0],
                            "eig0": self._last_eig[0],
                            "eig1": self._last_eig[1],
                            "sigma": self._last_sigma,
                            "radius": self._radius,
                        }
                    )
                slack_change = abs(accepted.slack - ro.slack)
                prev_merit = ro.merit
                ro = accepted
                # Stagnation (see FastSolverOptions.acceptable_tol): the merit has fallen by
                # next to nothing in each of the last acceptable_iter iterations.
                small = prev_merit - ro.merit <= opt.acceptable_tol * (1.0 + abs(ro.merit))
                acceptable = acceptable + 1 if small else 0
                if acceptable >= opt.acceptable_iter:
                    status, success = "Solved_To_Acceptable_Level", True
                    break
                if rival is not None and self._bound_for(rival, u, ro, abandon_above):
                    status = "Duplicate"
                    break
                # A trust region (or, without one, Levenberg-Marquardt damping) keeps steps
                # where the quadratic model holds: after heavy backtracking or a poor model
                # ratio (negative curvature floored, strongly curved constraints) the next
                # steps are shorter; good full steps lift the limit again, so the local
                # convergence stays fast.
                at_radius = False
                if opt.trust_radius > 0.0:
                    # The QP model's predicted decrease against the actual one at the full step.
                    size = float(np.max(np.abs(d) / self._range))
                    at_radius = cut  # (the radius has not changed since)
                    model_ratio = (prev_merit - ro.merit) / predicted if predicted > 0 else 1.0
                    if t < 1.0 or model_ratio < 0.25:
                        self._radius = max(0.5 * t * size, opt.min_trust_radius)
                    elif model_ratio > 0.25 and at_radius:
                        self._radius = min(2.0 * self._radius, 1.0)
                elif t < opt.damping_threshold:
                    damping = max(10.0 * damping, opt.damping_init)
                elif t == 1.0:
                    damping = (
                        opt.damping_decrease * damping if damping > 1e-3 * opt.damping_init else 0.0
                    )
                ratio = step / prev_step if math.isfinite(prev_step) else 1.0
                # (a step cut by the trust region says nothing about convergence)
                predicted_next = step * min(ratio, 1.0) if t == 1.0 and not at_radius else math.inf
                prev_step = step if t == 1.0 else math.inf
                if predicted_next <= opt.final_step_tol and (
                    ro.slack <= opt.add_tol or slack_change <= opt.add_tol * (1.0 + ro.slack)
                ):
                    status, success = "Solve_Succeeded", True
                    break
        except _OutOfTime:  # inside an iteration: keep the last accepted iterate
            status, success = "Maximum_WallTime_Exceeded", False
        self._spare_lin = lin
        return ro, status, success, iterations, stats


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


__all__ = ["HESSIAN_MODIFICATIONS", "RESTARTS", "FastScenarioSolver", "FastSolverOptions"]
