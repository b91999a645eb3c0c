"""The subproblem of one fast-SQP iteration: the convexified Hessian and the QP step.

Given the linearisation at the current inputs, :class:`SubproblemMixin` makes the
Hessian of the Lagrangian positive definite (first by ``sigma J_A' J_A`` of the
constraints predicted active, which leaves the QP step on that active set unchanged,
else by raising eigenvalues to a floor), screens the scenario rows that can become
active, and solves the dense QP (:class:`~controllers.solvers.fast.qp.slot_qp.SlotQP`) with
check-and-add over every scenario row, so the step is the full QP's. The SQP loop
around it is :class:`controllers.solvers.fast.solver.FastScenarioSolver` (the line search and
trust region: :mod:`controllers.solvers.fast.globalisation`; the extra starts:
:mod:`controllers.solvers.fast.restarts`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.linalg.lapack

from controllers.problem import ScenarioProblem
from controllers.solvers.fast.condensed import CondensedModel
from controllers.solvers.fast.iterate import Linearisation, Rollout
from controllers.solvers.fast.options import FastSolverOptions
from controllers.solvers.fast.qp.hard_qp import DaqpHardQP
from controllers.solvers.fast.qp.slot_qp import SlotQP

QP = SlotQP | DaqpHardQP  # a QP object of one check-and-add round


@dataclass
class QPStep:
    """Solution of one SQP subproblem."""

    d: np.ndarray  # (N nu,) input step
    slack_sum: float  # sum of the QP's slacks
    pos: np.ndarray  # (r, 3) scenario rows (constraint, step, scenario) in the QP
    lam: np.ndarray  # (r,) their multipliers
    qp: QP  # the QP object (for a second-order correction)
    row: np.ndarray  # (r,) their row slots in it
    s_pos: np.ndarray  # (ng, N) slack of each (constraint, step) group
    s_shared: np.ndarray  # (n_shared,) slack of each shared row, ordered (step, constraint)
    lam_shared: np.ndarray  # (n_shared,) multipliers of the shared rows
    curvature: float = 0.0  # d' H_qp d of the QP's (convexified) Hessian


class SolverAttributes:
    """What the mixins of :class:`~controllers.solvers.fast.solver.FastScenarioSolver` read
    of it: its problem, options, condensed model (``condensed``), input bounds and trust radius
    (set by the solver's ``__init__`` and SQP loop), and its deadline check."""

    problem: ScenarioProblem
    options: FastSolverOptions
    condensed: CondensedModel
    _n_u: int  # inputs of the horizon, N nu
    _lower: np.ndarray  # (N nu,) input bounds
    _upper: np.ndarray
    _range: np.ndarray  # (N nu,) each input's range (inf: none)
    _radius: float  # current trust radius (fraction of the range; 0: none)
    _deadline: float  # time.perf_counter() value ending the current solve (QP budgets)

    def _check_time(self) -> None:  # the solver's deadline check
        raise NotImplementedError


class SubproblemMixin(SolverAttributes):
    """The QP subproblem of :class:`~controllers.solvers.fast.solver.FastScenarioSolver`.

    A base class of the solver: it reads the solver's attributes (:class:`SolverAttributes`
    and those declared below) and keeps the QP objects by size (``_qps``).
    """

    _n_shared: int  # shared rows, ordered (step, shared constraint)
    _a_shared: np.ndarray  # (n_shared, N nu) their Jacobian rows
    _n_groups: int  # (constraint, step) groups of scenario rows
    _eye: np.ndarray  # (N nu, N nu) identity
    _floor_eye: np.ndarray  # hessian_floor times it
    _hard_solver: str  # the solver of the QPs without slacks (resolve_qp_solver)
    _qps: dict[tuple[int, int, bool], QP]
    _hard_first: bool  # try the QP without slacks first (elastic_qp="on_demand")
    _last_eig: Any  # diagnostics of the last convexification (for the trace)
    trace: list[dict[str, Any]] | None  # per-iteration diagnostics, when asked for
    _last_sigma: float

    # ------------------------------------------------------------------ convexification

    def _convexify(
        self,
        H: np.ndarray,
        lin: Linearisation,
        active_pos: np.ndarray,
        active_shared: np.ndarray,
        active_bounds: np.ndarray,
    ) -> tuple[np.ndarray, float, np.ndarray]:
        """A positive definite QP Hessian that leaves the Newton step unchanged if it can.

        The Lagrangian's Hessian is often indefinite although it is positive definite on
        the null space of the active constraints (second-order sufficiency). Adding
        ``sigma J_A' J_A`` for the constraints ``A`` predicted active (hard-active rows and
        input bounds of the previous QP) then makes it positive definite without changing
        the QP's solution on that active set: only its multipliers shift, by
        ``sigma J_A d``. If that is not enough, eigenvalues below ``hessian_floor`` are
        raised to it.

        Returns:
            ``(H_qp, sigma, J_pos)`` with ``J_pos`` the Jacobian rows of ``active_pos``
            (``sigma = 0`` when no augmentation was used).
        """
        floor = self.options.hessian_floor
        j_pos = np.empty((0, self._n_u))
        shifted = self._floor_eye
        if self.trace is None:
            # Every eigenvalue at or above the floor: a Cholesky factor of H - floor I exists
            # (the common case at N = 7; an eighth of an eigen-decomposition's time).
            if _positive_definite(H - shifted):
                return H, 0.0, j_pos
        w, V = np.linalg.eigh(H)
        self._last_eig = (float(w[0]), float(w[-1]))
        if w[0] >= floor:
            return H, 0.0, j_pos
        rows = []
        if active_pos.shape[0]:
            j_pos = self.condensed.rows(lin, active_pos)[0]
            rows.append(j_pos)
        if active_shared.size:
            rows.append(self._a_shared[active_shared])
        if active_bounds.size:
            rows.append(self._eye[active_bounds])
        # Adding sigma J'J of rank r moves at most r eigenvalues above the floor (interlacing):
        # with fewer rows than eigenvalues below it no sigma does it, and only "augmented"
        # uses the augmented matrix all the same.
        augmented = self.options.hessian_modification == "augmented"
        if rows and (augmented or sum(r.shape[0] for r in rows) >= np.count_nonzero(w < floor)):
            J = np.vstack(rows)
            G = J.T @ J
            sigma = float(np.max(np.abs(w))) / max(float(np.max(np.diag(G))), 1e-12)
            for _ in range(4):
                H_aug = H + sigma * G
                # All eigenvalues above the floor: a Cholesky factor of H_aug - floor I exists
                # (only a yes or no is needed).
                if _positive_definite(H_aug - shifted):
                    return H_aug, sigma, j_pos
                if augmented:
                    # Negative curvature left on the active constraints' null space: raise
                    # only those eigenvalues, keeping the constraints' own curvature.
                    w_aug, V_aug = np.linalg.eigh(H_aug)
                    return (V_aug * np.maximum(w_aug, floor)) @ V_aug.T, sigma, j_pos
                sigma *= 10.0
        if self.options.hessian_modification == "abs":
            return (V * np.maximum(np.abs(w), floor)) @ V.T, 0.0, j_pos
        return (V * np.maximum(w, floor)) @ V.T, 0.0, j_pos

    # ------------------------------------------------------------------ QP subproblem

    def _qp(self, rows: int, groups: int, elastic: bool = True) -> QP:
        """The cached QP with room for ``rows`` scenario rows in ``groups`` groups (with
        slacks; ``elastic=False``: the same rows without any slack).

        Capacities are rounded up to powers of two, so a few QP objects serve every solve
        and each keeps its own hot-start information and slot assignment. The QP without
        slacks on DAQP (``"auto"``'s choice) is one :class:`DaqpHardQP` for every size: DAQP
        is cold-started at every call, so it needs no slots.
        """
        p, opt = self.problem, self.options
        if not elastic and self._hard_solver == "daqp":
            qp = self._qps.get((0, 0, False))
            if qp is None:
                qp = self._qps[0, 0, False] = DaqpHardQP(self._n_u, self._n_shared, opt.max_time)
            return qp
        groups = min(max(4, 1 << (groups - 1).bit_length()), self._n_groups) if elastic else 0
        rows = max(8, 1 << (rows - 1).bit_length())
        key = (rows, groups, elastic)
        qp = self._qps.get(key)
        if qp is None:
            qp = SlotQP(
                self._n_u,
                self._n_shared,
                rows,
                groups,
                opt.qp_solver,
                p.slack_penalty,
                opt.slack_regularisation,
                max_time=opt.max_time,
                elastic=elastic,
            )
            self._qps[key] = qp
        return qp

    def _screen(self, ro: Rollout) -> np.ndarray:
        """Initial scenario rows ``(r, 3)`` of ``(constraint, step index, scenario)``.

        In every (constraint, step) group whose largest value lies within
        ``screen_margin`` of activity: the ``screen_rows`` largest values within that
        margin, the scenario with the smallest value, and the scenarios extreme in each
        state the constraint depends on (scenarios differ mostly in how far they get along
        similar paths, so a step can make the other end of that family the worst one).
        """
        opt = self.options
        return self.condensed.screen(ro, opt.screen_margin, opt.screen_rows)

    def _missing_rows(
        self, lin: Linearisation, d: np.ndarray, s_pos: np.ndarray, pos: np.ndarray
    ) -> np.ndarray:
        """Scenario rows of the full QP violated at the step ``(d, s_pos)``.

        Up to ``screen_rows`` of the worst per (constraint, step) group, so that rows that
        are close together enter in one round.
        """
        opt = self.options
        return self.condensed.violated_rows(lin, d, s_pos, pos, opt.add_tol, opt.screen_rows)

    def _solve_qp(
        self,
        lin: Linearisation,
        H: np.ndarray,
        u: np.ndarray,
        pos: np.ndarray,
        g_shared: np.ndarray,
        stats: dict,
    ) -> QPStep | None:
        """Step of the full QP by check-and-add over the scenario rows; None on failure.

        ``g_shared``: the shared rows' values, ordered (step, constraint).

        With ``_hard_first`` each round first solves the QP without slacks. Its step is the
        exact-penalty QP's step when it is feasible and no multiplier exceeds the slack
        penalty ``rho`` (for the rows of a group, their sum): then ``s = 0`` with those
        multipliers satisfies the elastic QP's optimality conditions (``rho - sum lambda >=
        0`` is the multiplier of ``s >= 0``), and that QP is strictly convex in the step.
        Otherwise this round and the rest of the iteration use the QP with slacks.
        """
        p, nu, n_sh = self.problem, self._n_u, self._n_shared
        n, ng = p.horizon, self.condensed.n_rows  # (with feedback: the input rows too)
        n_scen = lin.ro.X.shape[2]
        hard = self._hard_first
        lo, hi = self._lower - u, self._upper - u
        if self._radius > 0.0:
            lo = np.maximum(lo, -self._radius * self._range)
            hi = np.minimum(hi, self._radius * self._range)
        # The rows' Jacobians and values, extended by each round's new rows only.
        a_pos, g_pos = self.condensed.rows(lin, pos)
        for round_ in range(self.options.max_qp_rounds):
            self._check_time()
            group = pos[:, 0] * n + pos[:, 1]
            s_pos = np.zeros((ng, n))
            this_round = (H, lin.grad, lo, hi, g_shared, group * n_scen + pos[:, 2], group)
            if hard:
                qp = self._qp(max(pos.shape[0], 1), 1, elastic=False)
                row, _ = self._load(qp, *this_round, a_pos, g_pos)
                d, lam_all, ok = qp.solve(self._deadline)
                self._count(stats, qp)
                rho = p.slack_penalty
                ok = (
                    ok
                    and bool(np.all(lam_all[:n_sh] <= rho))
                    and float(np.bincount(group, lam_all[row], minlength=1).max(initial=0.0)) <= rho
                )
                if ok:
                    z = np.concatenate([d, np.zeros(n_sh)])
                else:
                    hard = False
                    stats["qp_hard_rejected"] += 1
            if not hard:
                n_groups = np.unique(group).size
                qp = self._qp(max(pos.shape[0], 1), max(n_groups, 1))
                row, column = self._load(qp, *this_round, a_pos, g_pos)
                retried = qp.failures
                z, lam_all, ok = qp.solve(self._deadline)
                self._count(stats, qp)
                stats["qp_retries"] += qp.failures - retried
                if not ok:
                    return None
                s_pos.reshape(-1)[group] = z[nu + n_sh + column]
            missing = self._missing_rows(lin, z[:nu], s_pos, pos)
            if missing.shape[0] == 0:
                break
            if round_ == self.options.max_qp_rounds - 1:  # keep the last QP's rows
                stats["qp_rounds_exhausted"] += 1
                break
            pos = np.concatenate([pos, missing])
            a_new, g_new = self.condensed.rows(lin, missing)
            a_pos, g_pos = np.concatenate([a_pos, a_new]), np.concatenate([g_pos, g_new])
        stats["qp_rows"] = max(stats["qp_rows"], pos.shape[0])
        return QPStep(
            d=z[:nu],
            slack_sum=float(z[nu:].sum()),
            pos=pos,
            lam=lam_all[row],
            qp=qp,
            row=row,
            s_pos=s_pos,
            s_shared=z[nu : nu + n_sh],
            lam_shared=lam_all[:n_sh],
        )

    def _load(
        self,
        qp: QP,
        H: np.ndarray,
        grad: np.ndarray,
        lo: np.ndarray,
        hi: np.ndarray,
        g_shared: np.ndarray,
        keys: np.ndarray,
        group: np.ndarray,
        a_pos: np.ndarray,
        g_pos: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """One round's QP into ``qp``; the rows' slots and slack columns (:meth:`SlotQP.assign`)."""
        row, column = qp.assign(keys, group)
        qp.set_problem(H, grad, lo, hi, self._a_shared, g_shared)
        qp.set_position_rows(row, column, a_pos, g_pos)
        return row, column

    @staticmethod
    def _count(stats: dict, qp: QP) -> None:
        """Count one QP solve (by solver; hard QPs also apart)."""
        stats["qp_solves"] += 1
        stats["qp_calls"][qp.solver] = stats["qp_calls"].get(qp.solver, 0) + 1
        if not qp.elastic:
            stats["qp_hard"] += 1

    def _newton_step(
        self,
        lin: Linearisation,
        H: np.ndarray,
        u: np.ndarray,
        active_pos: np.ndarray,
        active_shared: np.ndarray,
        damping: float,
        stats: dict,
    ) -> tuple[QPStep | None, np.ndarray]:
        """QP step with a convexified Hessian, and the scenario-row multipliers ``(ng, N, Ns)``.

        A constraint predicted active whose row the QP leaves slack (or whose multiplier
        turns negative) would have bent the step through the augmentation: it is dropped
        and the QP re-solved. ``damping`` (Levenberg-Marquardt) is added to the Hessian.
        """
        p = self.problem
        mu = np.zeros((self.condensed.n_rows, p.horizon, lin.ro.X.shape[2]))
        bounds = np.nonzero((u <= self._lower + 1e-12) | (u >= self._upper - 1e-12))[0]
        screened = self._screen(lin.ro)
        g_shared = lin.ro.G[self.condensed.shared].max(axis=2).T.ravel()
        for attempt in range(4):
            if attempt == 3:  # give up predicting: plain eigenvalue clipping
                active_pos, active_shared, bounds = active_pos[:0], active_shared[:0], bounds[:0]
            H_qp, sigma, j_pos = self._convexify(H, lin, active_pos, active_shared, bounds)
            self._last_sigma = sigma if sigma > 0 else (-1.0 if H_qp is not H else 0.0)
            if damping > 0.0:
                H_qp = H_qp + damping * self._eye
            step = self._solve_qp(lin, H_qp, u, screened, g_shared, stats)
            if step is None:
                return None, mu
            step.curvature = float(step.d @ H_qp @ step.d)
            mu[:] = 0.0
            mu[step.pos[:, 0], step.pos[:, 1], step.pos[:, 2]] = step.lam
            if sigma == 0.0:
                return step, mu
            d, tol = step.d, 1e-8
            idx = (active_pos[:, 0], active_pos[:, 1], active_pos[:, 2])
            lin_d = j_pos @ d
            lam = mu[idx] + sigma * lin_d  # multipliers of the un-augmented QP
            keep_pos = (lam >= -tol) & (
                lin.ro.G[idx] + lin_d - step.s_pos[active_pos[:, 0], active_pos[:, 1]] >= -tol
            )
            mu[idx] = np.maximum(lam, 0.0)
            sh_d = self._a_shared[active_shared] @ d
            keep_shared = (step.lam_shared[active_shared] + sigma * sh_d >= -tol) & (
                g_shared[active_shared] + sh_d - step.s_shared[active_shared] >= -tol
            )
            u_new = u[bounds] + d[bounds]
            keep_bounds = (u_new <= self._lower[bounds] + 1e-10) | (
                u_new >= self._upper[bounds] - 1e-10
            )
            if keep_pos.all() and keep_shared.all() and keep_bounds.all():
                return step, mu
            active_pos = active_pos[keep_pos]
            active_shared = active_shared[keep_shared]
            bounds = bounds[keep_bounds]
        return step, mu


def _positive_definite(M: np.ndarray) -> bool:
    """Whether the symmetric ``M`` has a Cholesky factor (LAPACK's ``dpotrf`` on its lower
    triangle, without NumPy's exception on failure: 1-3 us against 5-7 us at 14-30 rows).
    ``M`` may be overwritten: pass a temporary."""
    return _DPOTRF(M, lower=1, clean=0, overwrite_a=1)[1] == 0


_DPOTRF = scipy.linalg.lapack.dpotrf

__all__ = ["QP", "QPStep", "SolverAttributes", "SubproblemMixin"]
