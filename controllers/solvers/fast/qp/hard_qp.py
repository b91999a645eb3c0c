"""The fast SQP's QP without slacks on DAQP, straight from the caller's arrays.

The check-and-add rounds of :mod:`controllers.solvers.fast.subproblem` first solve the QP
on the inputs alone, rows ``J_r d <= -g_r`` (the shared rows, then the scenario rows), with
DAQP cold-started. DAQP keeps nothing from one call to the next, so the padded row slots of
:class:`~controllers.solvers.fast.qp.slot_qp.SlotQP` (made for qpOASES's hot starts) only cost
copies here: :class:`DaqpHardQP` hands DAQP the rows as the caller built them, in the same
order and with the same bounds, so DAQP gets the very QP it got through ``SlotQP`` and
returns the same step, bit for bit. Measured on 300 of these QPs recorded in the paper's
closed loop (N = 7): 22 against 38 us per call, DAQP's own work included.
"""

from __future__ import annotations

import math
import time

import numpy as np

from controllers.solvers.fast.qp.slot_qp import (
    DAQP_PRIMAL_TOL,
    INF_BOUND,
    _available,
    _daqp_time_limit,
)


class DaqpHardQP:
    """The QP without slacks, ``min d'H d / 2 + grad'd`` over ``lower <= d <= upper`` and
    rows ``A d <= b``, on DAQP.

    The subset of :class:`~controllers.solvers.fast.qp.slot_qp.SlotQP`'s interface that the fast SQP
    uses for a QP without slacks (``elastic=False``): :meth:`assign`, :meth:`set_problem`,
    :meth:`set_position_rows`, :meth:`set_position_bounds` (second-order corrections),
    :meth:`solve`, :meth:`reset`, and the attributes ``solver``, ``elastic``, ``failures``.
    The arrays given are held, not copied: the caller must not change them before the last
    :meth:`solve` on them (the SQP builds new ones for every round).

    Args:
        n_u: the inputs ``N nu``.
        n_shared: the shared rows (they come first among the rows).
        max_time: DAQP's time limit per call [s] (``inf``: none).

    Raises:
        ValueError: when the daqp package is missing.
    """

    solver = "daqp"
    elastic = False
    failures = 0  # (a failed QP without slacks is not retried: the elastic QP takes over)

    def __init__(self, n_u: int, n_shared: int, max_time: float = math.inf) -> None:
        if not _available("daqp"):
            raise ValueError("qp_solver='daqp' needs the daqp package (pip install daqp)")
        import daqp

        self._daqp = daqp
        self.n_u, self.n_speed = n_u, n_shared
        self.max_time = max_time
        empty = np.empty(0)
        self._H, self._grad, self._bu, self._bl = empty, empty, empty, empty
        self._a_speed, self._ub_speed = np.empty((0, n_u)), empty
        self._a_pos, self._ub_pos = np.empty((0, n_u)), empty

    def reset(self) -> None:
        """Nothing to forget: every call starts cold."""

    def assign(self, keys: np.ndarray, groups: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The rows' indices among all rows (after the shared ones), in the order given; no
        slack columns (``-1``)."""
        k = len(keys)
        return self.n_speed + np.arange(k), np.full(k, -1)

    def set_problem(
        self,
        H: np.ndarray,
        grad: np.ndarray,
        lower: np.ndarray,
        upper: np.ndarray,
        a_speed: np.ndarray,
        g_speed: np.ndarray,
    ) -> None:
        """Hessian, gradient, step bounds and the shared rows ``a_speed d <= -g_speed``."""
        self._H, self._grad = np.ascontiguousarray(H), grad
        self._bu = np.minimum(upper, INF_BOUND)
        self._bl = np.maximum(lower, -INF_BOUND)
        self._a_speed, self._ub_speed = a_speed, -g_speed

    def set_position_rows(
        self, row: np.ndarray, column: np.ndarray, a_pos: np.ndarray, g_pos: np.ndarray
    ) -> None:
        """The scenario rows ``a_pos d <= -g_pos`` in the order :meth:`assign` gave."""
        self._a_pos, self._ub_pos = a_pos, -g_pos

    def set_position_bounds(self, row: np.ndarray, g_pos: np.ndarray) -> None:
        """Change only the constant terms of the given rows (second-order correction)."""
        self._ub_pos[row - self.n_speed] = -g_pos

    def solve(self, deadline: float = math.inf) -> tuple[np.ndarray, np.ndarray, bool]:
        """Solve the QP: ``(d, row multipliers >= 0, success)``; the multipliers of the
        shared rows first, then the scenario rows'. Rows without a finite bound are left
        out (multiplier 0); on failure ``d`` is NaN and the multipliers 0. ``deadline`` (a
        ``time.perf_counter()`` value, the solve's end) limits DAQP's time; once it has
        passed the QP fails at once."""
        nu = self.n_u
        left = deadline - time.perf_counter() if math.isfinite(deadline) else math.inf
        if left <= 0.0:
            return np.full(nu, np.nan), np.zeros(self._ub_speed.size + self._ub_pos.size), False
        ub = np.concatenate([self._ub_speed, self._ub_pos])
        A = np.concatenate([self._a_speed, self._a_pos])
        kept = ub < np.inf
        every = bool(kept.all())
        if not every:
            A, ub_rows = A[kept], ub[kept]
        else:
            ub_rows = ub
        bu = np.concatenate([self._bu, ub_rows])
        bl = np.concatenate([self._bl, np.full(ub_rows.size, -INF_BOUND)])
        x, _, flag, info = self._daqp.solve(
            self._H,
            self._grad,
            A,
            bu,
            bl,
            primal_tol=DAQP_PRIMAL_TOL,
            time_limit=_daqp_time_limit(left, self.max_time),
        )
        lam = np.zeros(ub.size)
        if flag not in (1, 2):  # 1, 2: optimal, soft-optimal; < 0: infeasible, cycling, limits
            return np.full(nu, np.nan), lam, False
        if every:
            lam[:] = info["lam"][nu:]
        else:
            lam[kept] = info["lam"][nu:]
        d = np.array(x, dtype=float)
        return d, np.maximum(lam, 0.0), bool(np.all(np.isfinite(d)))


__all__ = ["DaqpHardQP"]
