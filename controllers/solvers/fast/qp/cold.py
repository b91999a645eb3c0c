"""The cold-started QP solvers of :class:`~controllers.solvers.fast.qp.slot_qp.SlotQP`: DAQP,
PIQP, the elastic interior point and CasADi's qrqp, each on the rows in use, each with the
iteration or time limit its :class:`~controllers.solvers.fast.qp.budget.QPBudget` allows."""

from __future__ import annotations

import math
import time

import casadi as ca
import numpy as np

from controllers.solvers.fast.qp import elastic_ipm
from controllers.solvers.fast.qp.budget import QPBudget

# DAQP's and PIQP's infinity: a bound at or beyond it is none.
INF_BOUND = 1e30
# DAQP's primal feasibility tolerance [m, m/s]: below the SQP's check-and-add tolerance,
# so that rows close to a QP row are not added round after round (DAQP's default is 1e-6).
DAQP_PRIMAL_TOL = 1e-10
PIQP_EPS_ABS = 1e-9  # PIQP's absolute tolerance on the KKT residuals
PIQP_EPS_REL = 1e-12
# qrqp's iteration limit when time is no object (CasADi's default).
QRQP_MAX_ITER = 1000


def _daqp_time_limit(left: float, max_time: float) -> float:
    """DAQP's ``time_limit`` [s] from the solve's time left and the QP's own limit (0: none)."""
    limit = min(left, max_time)
    return limit if math.isfinite(limit) else 0.0


class ColdSolvers:
    """The cold-started solvers of a :class:`~controllers.solvers.fast.qp.slot_qp.SlotQP` (a
    mixin: it reads the QP's arrays ``H``, ``g``, ``A``, ``uba``, ``lbx``, ``ubx``, writes
    ``x`` and ``lam_a``, and keeps the ``budget``)."""

    H: np.ndarray
    g: np.ndarray
    A: np.ndarray
    uba: np.ndarray
    lbx: np.ndarray
    ubx: np.ndarray
    x: np.ndarray
    lam_a: np.ndarray
    n_u: int
    n_var: int
    max_time: float
    budget: QPBudget
    _bu: np.ndarray
    _bl: np.ndarray
    _slack_of_row: np.ndarray

    def _solve_qrqp(self) -> bool:
        """CasADi's active-set QP solver qrqp on the rows in use (a fallback)."""
        rows = np.flatnonzero(self.uba < np.inf)
        nv, m = self.n_var, rows.size
        max_iter = self.budget.iterations("qrqp", nv, m, QRQP_MAX_ITER)
        self.lam_a[:] = 0.0
        if max_iter < 1:
            self.x[:] = np.nan
            return False
        t0 = time.perf_counter()
        conic = ca.conic(
            "fast_sqp_qrqp",
            "qrqp",
            {"h": ca.Sparsity.dense(nv, nv), "a": ca.Sparsity.dense(m, nv)},
            {
                "print_iter": False,
                "print_header": False,
                "error_on_fail": False,
                "max_iter": int(max_iter),
            },
        )
        a = self.A[rows]
        res = conic(h=self.H, g=self.g, a=a, uba=self.uba[rows], lbx=self.lbx, ubx=self.ubx)
        iters = int(conic.stats().get("iter_count", max_iter))
        self.budget.record("qrqp", nv, m, time.perf_counter() - t0, iters)
        x = np.asarray(res["x"]).ravel()
        if not conic.stats()["success"] or not np.all(np.isfinite(x)):
            self.x[:] = np.nan
            return False
        self.x[:] = x
        self.lam_a[rows] = np.asarray(res["lam_a"]).ravel()
        return True

    def _solve_daqp(self) -> bool:
        """DAQP on the rows in use (finite ``uba``), cold started."""
        import daqp

        rows = self._rows_and_bounds()
        nv, m = self.n_var, rows.size
        left = self.budget.remaining()
        if left <= 0.0:
            self.budget.refused += 1
            return self._store(False, self.x, rows, self.lam_a)
        bu, bl = self._bu[: nv + m], self._bl[: nv + m]
        bu[nv:] = self.uba[rows]
        bl[nv:] = -INF_BOUND
        x, _, flag, info = daqp.solve(
            self.H,
            self.g,
            np.ascontiguousarray(self.A[rows]),
            bu,
            bl,
            primal_tol=DAQP_PRIMAL_TOL,
            time_limit=_daqp_time_limit(left, self.max_time),
        )
        # flag 1, 2: optimal, soft-optimal; < 0: infeasible, cycling, limits
        return self._store(flag in (1, 2), x, rows, info["lam"][nv:])

    def _solve_piqp(self) -> bool:
        """PIQP (proximal interior point, dense) on the rows in use, cold started."""
        import piqp

        rows = self._rows_and_bounds()
        nv = self.n_var
        qp = piqp.DenseSolver()
        max_iter = self.budget.iterations("piqp", nv, rows.size, qp.settings.max_iter)
        if max_iter < 1:
            return self._store(False, self.x, rows, self.lam_a)
        qp.settings.max_iter = max_iter
        qp.settings.eps_abs = PIQP_EPS_ABS
        qp.settings.eps_rel = PIQP_EPS_REL
        t0 = time.perf_counter()
        qp.setup(
            np.asfortranarray(self.H),
            self.g,
            None,
            None,
            np.asfortranarray(self.A[rows]),
            None,
            self.uba[rows],
            self._bl[:nv],
            self._bu[:nv],
        )
        solved = qp.solve() == piqp.PIQP_SOLVED
        seconds = time.perf_counter() - t0
        self.budget.record("piqp", nv, rows.size, seconds, int(qp.result.info.iter))
        return self._store(solved, qp.result.x, rows, qp.result.z_u)

    def _solve_elastic_ipm(self) -> bool:
        """The project's structured interior point (:mod:`~controllers.solvers.fast.qp.elastic_ipm`)
        on the rows in use, cold started: the slacks eliminated, an ``n_u x n_u`` system
        per iteration. It has no time limit of its own: at most
        :data:`~controllers.solvers.fast.qp.elastic_ipm.MAX_ITERATIONS` iterations (~0.1 ms each
        at N = 30), fewer when the time left allows fewer."""
        rows = np.flatnonzero(self.uba < np.inf)
        nu = self.n_u
        max_iter = self.budget.iterations("elastic_ipm", nu, rows.size, elastic_ipm.MAX_ITERATIONS)
        if max_iter < 1:
            return self._store(False, self.x, rows, self.lam_a)
        t0 = time.perf_counter()
        used, col = np.unique(self._slack_of_row[rows], return_inverse=True)
        slack = nu + used
        res = elastic_ipm.solve_elastic_qp(
            self.H[:nu, :nu],
            self.g[:nu],
            self.lbx[:nu],
            self.ubx[:nu],
            self.A[rows, :nu],
            self.uba[rows],
            col,
            self.g[slack],
            self.H[slack, slack],
            eps_abs=PIQP_EPS_ABS,
            eps_rel=PIQP_EPS_REL,
            max_iter=max_iter,
        )
        seconds = time.perf_counter() - t0
        self.budget.record("elastic_ipm", nu, rows.size, seconds, res.iterations)
        x = np.zeros(self.n_var)
        x[:nu] = res.d
        x[slack] = res.s
        return self._store(res.solved, x, rows, res.z)

    def _rows_and_bounds(self) -> np.ndarray:
        """The rows in use (finite ``uba``); the simple bounds, clipped to
        ``+-INF_BOUND``, into the first ``n_var`` entries of ``_bl`` and ``_bu``."""
        nv = self.n_var
        np.minimum(self.ubx, INF_BOUND, out=self._bu[:nv])
        np.maximum(self.lbx, -INF_BOUND, out=self._bl[:nv])
        return np.flatnonzero(self.uba < np.inf)

    def _store(self, solved: bool, x: np.ndarray, rows: np.ndarray, lam: np.ndarray) -> bool:
        """Keep a cold-started solver's result (``x``, the multipliers ``lam`` of ``rows``);
        True if it solved with a finite step."""
        self.lam_a[:] = 0.0
        if not solved:
            self.x[:] = np.nan
            return False
        self.x[:] = x
        self.lam_a[rows] = lam
        return bool(np.all(np.isfinite(self.x)))


__all__ = ["DAQP_PRIMAL_TOL", "INF_BOUND", "QRQP_MAX_ITER", "ColdSolvers"]
