"""The dense QP of the fast SQP solver, in fixed row slots so that hot starts mean something.

Used by :mod:`controllers.solvers.fast.solver`.
QP solvers (:data:`QP_SOLVERS`):

* ``"auto"`` (the fast solver's default): qpOASES for QPs with fewer than
  :data:`AUTO_IPM_VARIABLES` variables, the elastic interior point for larger ones (PIQP
  from :data:`AUTO_PIQP_VARIABLES` on where no C compiler works), and DAQP for the QPs
  without slacks (:func:`resolve_qp_solver`): those are small (the inputs only) and often
  infeasible, which a cold dual active set finds out fast, and a failure of theirs costs
  only the QP with slacks.
* ``"elastic_ipm"``: the project's interior point for this QP
  (:mod:`~controllers.solvers.fast.qp.elastic_ipm`, compiled C), cold started on the rows in use.
  It eliminates the slack columns (each row has exactly one), so it factorises an
  ``n_u x n_u`` matrix per iteration where PIQP factorises all variables. For the QPs
  with slacks only; those without go as with ``"auto"``.
* ``"qpoases"``: qpOASES through CasADi on every row slot, hot-started from the
  previous active set of the same object; :meth:`SlotQP.reset` forgets it (the fast
  solvers reset at every solve, so nothing carries over from one problem to the next).
* ``"piqp"``: the proximal interior-point solver PIQP (dense) on the rows in use only,
  cold started at every call. Its cost hardly depends on how many constraints change
  activity, which is what makes qpOASES slow on the large QPs of long horizons.
* ``"daqp"``: the dual active-set solver DAQP on the rows in use only, cold started at
  every call. It cycles on some degenerate QPs (many near-parallel scenario rows); those
  fall back as below.

A failed call is retried by the elastic interior point (unless it was the one that
failed), then by a cold qpOASES, then by CasADi's qrqp (which solves some degenerate QPs on
which qpOASES's factorisation breaks down), then both with a small proximal term on the
step (:meth:`SlotQP.solve`). Every call, retries included, gets an iteration or time limit
from what is left of the solve (:mod:`~controllers.solvers.fast.qp.budget`), and none is
made once nothing is left.
"""

from __future__ import annotations

import math
import time
from typing import Any

import casadi as ca
import numpy as np

from controllers.solvers.fast.qp import elastic_ipm
from controllers.solvers.fast.qp.budget import QPBudget
from controllers.solvers.fast.qp.cold import (  # (the constants also from here, as before)
    DAQP_PRIMAL_TOL,
    INF_BOUND,
    PIQP_EPS_ABS,
    PIQP_EPS_REL,
    ColdSolvers,
    _daqp_time_limit,
)
from controllers.solvers.quiet import silenced_output

QP_SOLVERS = ("auto", "daqp", "elastic_ipm", "piqp", "qpoases")
# Proximal terms on the step (relative to the largest Hessian diagonal entry) of the
# retries of a failed QP: none first.
PROXIMAL_STEPS = (0.0, 1e-8, 1e-4)
# "auto" without the compiled elastic interior point: QPs with at least this many variables
# (inputs of the horizon, shared slacks, group slack columns) go to PIQP, smaller ones to
# qpOASES. Measured per QP inside the SQP on the paper's closed-loop problems (median time
# per call, qpOASES hot-started / PIQP): 32-44 variables (N = 7) 0.11-0.23 / 0.25-0.44 ms;
# 76 (N = 15) 0.53 / 1.18 ms; 92 (N = 15) 2.8 / 1.8 ms; 181 (N = 30, ~400 rows, cold,
# offline) 124 / 9.2 ms.
AUTO_PIQP_VARIABLES = 80
# "auto" with it: QPs with slacks and at least this many variables go to the elastic
# interior point (elastic_ipm). On the recorded elastic QPs of the paper's closed loop
# (median per call, offline, against PIQP on the same QP): N = 7 (36-53 variables) 0.19 ms
# against qpOASES's 0.14 ms hot-started in the SQP (whole solves 1.03x with it); N = 15
# (76-109) 0.61 against PIQP's 1.28 ms and qpOASES's ~1.7 ms; N = 30 (184) 2.7 against 6.6 ms.
AUTO_IPM_VARIABLES = 64
# qpOASES memories a QP object keeps checked out (each has solved a QP) before it builds a
# new conic that frees them: a cold start needs a memory no QP has touched (SlotQP._fresh_memory).
# At most this many, and at most about MAX_SPENT_BYTES of them: one memory of a dense QP with
# nv variables and m rows measured ~16 nv (nv + m) bytes (40 kB at nv = 36, m = 30; 1.5 MB at
# nv = 184, m = 316).
MAX_SPENT_MEMORIES = 32
MAX_SPENT_BYTES = 4 << 20


def resolve_qp_solver(solver: str, n_var: int, elastic: bool = True) -> str:
    """The QP solver that ``solver`` stands for on a QP with ``n_var`` variables.

    ``"auto"``: on a QP without slacks (``elastic=False``) DAQP; else the project's
    elastic interior point from :data:`AUTO_IPM_VARIABLES` variables on where a C compiler
    works, PIQP from :data:`AUTO_PIQP_VARIABLES` on, qpOASES below (qpOASES wherever the
    package named is missing). ``"elastic_ipm"`` is only for QPs with slacks: those without
    go as with ``"auto"``. Other names stand for themselves.
    """
    if solver not in ("auto", "elastic_ipm"):
        return solver
    if not elastic:
        return "daqp" if _available("daqp") else "qpoases"
    if solver == "elastic_ipm" or (n_var >= AUTO_IPM_VARIABLES and _available("elastic_ipm")):
        return "elastic_ipm"
    return "piqp" if n_var >= AUTO_PIQP_VARIABLES and _available("piqp") else "qpoases"


def _available(package: str) -> bool:
    """Whether the optional QP package ``"daqp"`` or ``"piqp"`` imports, or (for
    ``"elastic_ipm"``) the compiled elastic QP solver builds."""
    if package == "elastic_ipm":
        return elastic_ipm.available()
    try:
        if package == "daqp":
            import daqp  # noqa: F401
        else:
            import piqp  # noqa: F401
    except ImportError:
        return False
    return True


class SlotQP(ColdSolvers):
    """The SQP's QP ``min 1/2 z'Hz + g'z  s.t.  A z <= uba, lbx <= z <= ubx`` in persistent slots.

    ``z = [d (n_u), s_shared (n_shared), s_pos (group_capacity)]``: the input step, one
    slack per shared row (a constraint whose row is the same for every scenario, one per
    step, e.g. the bicycle's speed bounds), and one slack column per scenario-row group
    (one group per constraint and step) that has rows. Rows ``[J_r, -e_slack] z <= -g_r``:
    first the shared rows, then ``row_capacity`` slots for scenario rows. Each scenario
    row keeps its slot (and each group its slack column) for as long as it stays in the QP
    (:meth:`assign`), so that qpOASES's hot start from the previous active set of the same
    object means something; unused slots are zero rows with ``uba = +inf``, and the slack
    of an unused column stays at zero (it has no row and only costs). The capacities are
    the rows and groups in use rounded up to powers of two by the caller, so the dense QP
    stays close to the rows it needs (a padded layout with the same slot count for every
    group made the QP at N = 30 up to eight times as tall as its rows in use). qpOASES is
    a CasADi conic evaluated through a ``FunctionBuffer`` on persistent NumPy arrays; DAQP
    gets the rows in use only.

    ``elastic=False`` makes the same QP without any slack (``z = d``, rows ``J_r d <= -g_r``):
    the fast SQP solves it first and falls back to the elastic QP only when it is infeasible
    or its multipliers exceed the slack penalty (see
    :meth:`~controllers.solvers.fast.subproblem.SubproblemMixin._solve_qp`). A failed call of
    a hard QP is not retried (it is usually infeasibility, which the elastic QP handles).
    """

    def __init__(
        self,
        n_u: int,
        n_shared: int,
        row_capacity: int,
        group_capacity: int,
        solver: str,
        slack_penalty: float,
        slack_reg: float,
        max_time: float = math.inf,
        elastic: bool = True,
    ) -> None:
        if solver not in QP_SOLVERS:
            raise ValueError(f"solver={solver!r}: must be one of {QP_SOLVERS}")
        if not elastic:
            group_capacity = 0
        self.elastic = elastic
        n_slack = n_shared + group_capacity if elastic else 0
        solver = resolve_qp_solver(solver, n_u + n_slack, elastic)
        if solver in ("daqp", "piqp") and not _available(solver):
            raise ValueError(
                f"qp_solver={solver!r} needs the {solver} package (pip install {solver})"
            )
        if solver == "elastic_ipm" and not _available(solver):
            raise ValueError("qp_solver='elastic_ipm' needs a working C compiler ($CC, cc or gcc)")
        self.solver = solver
        self.row_capacity, self.group_capacity = row_capacity, group_capacity
        self.n_u, self.n_speed = n_u, n_shared
        self.n_var = n_u + n_slack
        self.capacity = self.n_speed + row_capacity
        self.max_time = max_time
        # Each call's iteration or time limit, from what is left of the solve (solve()).
        self.budget = QPBudget()
        nv, cap, nu = self.n_var, self.capacity, self.n_u
        # qpOASES's working-set recalculations per call: its own default, 5 (nv + rows),
        # fewer when the time left allows fewer (the conic is rebuilt for that).
        self._nwsr_default = 5 * (nv + cap)
        self._nwsr = self._nwsr_default
        # Dense inputs are column-major nonzeros; H is symmetric, A is viewed transposed.
        self._h = np.zeros(nv * nv)
        self.H = self._h.reshape(nv, nv)
        self.H[np.arange(nu, nv), np.arange(nu, nv)] = slack_reg
        self._a = np.zeros(cap * nv)
        self.A = self._a.reshape(nv, cap).T
        if elastic:
            self.A[np.arange(self.n_speed), nu + np.arange(self.n_speed)] = -1.0
        self.g = np.zeros(nv)
        self.g[nu:] = slack_penalty
        self.lba = np.full(cap, -np.inf)
        self.uba = np.full(cap, np.inf)
        self.lbx = np.zeros(nv)
        self.ubx = np.full(nv, np.inf)
        self.x = np.zeros(nv)
        self.lam_a = np.zeros(cap)
        self.failures = 0  # calls whose first attempt failed (recovered or not)
        self.retried_with_ipm = 0  # of them, retried by the elastic interior point first
        # Persistent assignment: the key of the row in each slot, the group of each slack
        # column (-1: free).
        self._slot_key = np.full(row_capacity, -1, dtype=np.int64)
        self._col_key = np.full(group_capacity, -1, dtype=np.int64)
        # The slack column (among all slack columns) of each row: the shared rows' own,
        # then the scenario rows' group columns (set_position_rows).
        self._slack_of_row = np.zeros(cap, dtype=np.int64)
        self._slack_of_row[: self.n_speed] = np.arange(self.n_speed)
        self._conic: Any = None
        self._buffer: Any = None
        self._spent: list[tuple[Any, Any]] = []  # used memories, kept checked out
        self._spare_in: dict[str, np.ndarray] = {}  # arrays of the conic's unused inputs
        self._spare_out: dict[str, np.ndarray] = {}
        self.max_spent = max(1, min(MAX_SPENT_MEMORIES, MAX_SPENT_BYTES // (16 * nv * (nv + cap))))
        self._hot = False  # the conic has solved a QP (it then hot-starts)
        self._stale = False  # reset() was called: no hot start at the next call
        if solver == "qpoases":
            self._build_conic()
        # Finite simple bounds for DAQP and PIQP; DAQP reads the rows' bounds after them:
        # [bounds (nv), rows (<= cap)].
        self._bu = np.empty(nv + cap)
        self._bl = np.empty(nv + cap)

    def _build_conic(self) -> None:
        """A fresh qpOASES conic on this object's arrays (no hot-start information)."""
        nv, cap = self.n_var, self.capacity
        # One QP cannot be interrupted from Python: qpOASES stops itself after nWSR
        # working-set changes (its CPUtime option was not honoured through CasADi).
        opts: dict[str, Any] = {
            "error_on_fail": False,
            "printLevel": "none",
            "nWSR": int(self._nwsr),
        }
        self._buffer, self._spent = None, []  # (dropping the old conic frees its memories)
        with silenced_output():  # qpOASES prints a banner whenever a memory is created
            self._conic = ca.conic(
                "fast_sqp_qp",
                "qpoases",
                {"h": ca.Sparsity.dense(nv, nv), "a": ca.Sparsity.dense(cap, nv)},
                opts,
            )
        self._arg_order = list(self._conic.name_in())
        self._res_sizes = [
            (name, self._conic.nnz_out(i)) for i, name in enumerate(self._conic.name_out())
        ]
        self._fresh_memory()

    def _fresh_memory(self) -> None:
        """Point this object's calls at a new qpOASES memory of the same conic: a QP
        instance that has solved nothing, so the next call starts cold (``init``).

        CasADi hands a released memory to the next buffer as it is, hot-start
        information included, so the buffers used before stay checked out (in
        ``_spent``) until ``max_spent`` of them (:data:`MAX_SPENT_MEMORIES`,
        :data:`MAX_SPENT_BYTES`) are replaced by a whole new conic, which frees them.
        In the paper's closed loop a new memory and its arguments cost about a quarter of
        a new conic (measured inside the fast SQP: 0.38 ms per conic, of which 0.14 ms
        the conic's construction, 0.11 ms silencing its banner, 0.06 ms the arguments).
        """
        if self._conic is None:  # a DAQP / PIQP object's first qpOASES call (a retry)
            self._build_conic()
            return
        if self._buffer is not None:
            if len(self._spent) >= self.max_spent:
                self._buffer = None
                self._build_conic()
                return
            self._spent.append((self._buffer, self._evaluate))
        with silenced_output():  # the banner again, for the new memory
            self._buffer, self._evaluate = self._conic.buffer()
        inputs = {
            "h": self._h,
            "g": self.g,
            "a": self._a,
            "lba": self.lba,
            "uba": self.uba,
            "lbx": self.lbx,
            "ubx": self.ubx,
        }
        outputs = {"x": self.x, "lam_a": self.lam_a}
        # The buffer holds raw pointers: every array it sees stays alive with this object.
        for i, name in enumerate(self._arg_order):
            arr = inputs.get(name)
            if arr is None:
                if name not in self._spare_in:
                    self._spare_in[name] = np.zeros(self._conic.nnz_in(i))
                arr = self._spare_in[name]
            self._buffer.set_arg(i, memoryview(arr))
        for i, (name, size) in enumerate(self._res_sizes):
            arr = outputs.get(name)
            if arr is None:
                if name not in self._spare_out:
                    self._spare_out[name] = np.zeros(size)
                arr = self._spare_out[name]
            self._buffer.set_res(i, memoryview(arr))
        self._hot = False

    def reset(self) -> None:
        """Forget every hot-start information and slot assignment before the next call
        (qpOASES: a fresh memory, taken when this object is next used; DAQP has none)."""
        self._stale = True
        self._slot_key[:] = -1
        self._col_key[:] = -1

    @staticmethod
    def _place(keys: np.ndarray, held: np.ndarray) -> np.ndarray:
        """Slots of ``keys`` (unique) in the assignment ``held`` (updated in place).

        A key already held keeps its slot; slots whose key is not in ``keys`` are freed;
        new keys take free slots in order.
        """
        # A dict over the few held keys beats sorting arrays at these sizes (tens of keys).
        where = {k: i for i, k in enumerate(held.tolist()) if k >= 0}
        slot = [where.get(k, -1) for k in keys.tolist()]
        kept = set(slot)
        kept.discard(-1)
        if len(kept) < len(where):
            held[[i for i in where.values() if i not in kept]] = -1
        new = [i for i, s in enumerate(slot) if s < 0]
        if new:
            free = np.flatnonzero(held < 0)
            if len(new) > free.size:
                raise ValueError(f"{keys.size} keys do not fit {held.size} slots")
            free = free[: len(new)]
            held[free] = keys[new]
            for i, f in zip(new, free.tolist(), strict=True):
                slot[i] = f
        return np.array(slot, dtype=np.int64)

    def assign(self, keys: np.ndarray, groups: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Row slots and slack columns of scenario rows.

        Args:
            keys: ``(r,)`` unique ids of the rows (e.g. ``(group, scenario)`` flattened).
            groups: ``(r,)`` the group id of each row.

        Returns:
            ``(row, column)``: each row's index in ``A`` (after the shared rows) and the
            index of its group's slack column among the group columns. For qpOASES, rows
            and groups that were in the previous call keep their slots (its hot start);
            the cold-started solvers (DAQP, PIQP, the elastic interior point) take the rows
            in the order given and the groups in ascending order.

        Raises:
            ValueError: when the rows or groups exceed the capacities.
        """
        keys = np.asarray(keys, dtype=np.int64)
        if self.solver != "qpoases":  # nothing to keep between calls: no slot bookkeeping
            if keys.size > self.row_capacity:
                raise ValueError(f"{keys.size} keys do not fit {self.row_capacity} slots")
            rows = self.n_speed + np.arange(keys.size)
            if not self.elastic:
                return rows, np.full(keys.size, -1)
            group_ids, inverse = np.unique(np.asarray(groups, dtype=np.int64), return_inverse=True)
            if group_ids.size > self.group_capacity:
                raise ValueError(f"{group_ids.size} keys do not fit {self.group_capacity} slots")
            return rows, inverse
        if not self.elastic:  # no slack columns
            return self.n_speed + self._place(keys, self._slot_key), np.full(keys.size, -1)
        group_ids, inverse = np.unique(np.asarray(groups, dtype=np.int64), return_inverse=True)
        columns = self._place(group_ids, self._col_key)
        rows = self._place(keys, self._slot_key)
        return self.n_speed + rows, columns[inverse]

    def set_problem(
        self,
        H: np.ndarray,
        grad: np.ndarray,
        lower: np.ndarray,
        upper: np.ndarray,
        a_speed: np.ndarray,
        g_speed: np.ndarray,
    ) -> None:
        """Hessian, gradient, step bounds and the shared rows (all of them)."""
        nu, ns = self.n_u, self.n_speed
        self.H[:nu, :nu] = H
        self.g[:nu] = grad
        self.lbx[:nu] = lower
        self.ubx[:nu] = upper
        self.A[:ns, :nu] = a_speed
        self.uba[:ns] = -g_speed

    def set_position_rows(
        self, row: np.ndarray, column: np.ndarray, a_pos: np.ndarray, g_pos: np.ndarray
    ) -> None:
        """Fill the given row slots (from :meth:`assign`), each linked to its group's slack
        ``column``; every other slot becomes an inactive zero row (a slack column without
        a row stays at zero: it only costs)."""
        nu, ns = self.n_u, self.n_speed
        first = nu + ns
        self.A[ns:, :] = 0.0
        self.uba[ns:] = np.inf
        self.A[row, :nu] = a_pos
        if self.elastic:
            self.A[row, first + column] = -1.0
            self._slack_of_row[row] = ns + column
        self.uba[row] = -g_pos

    def set_position_bounds(self, row: np.ndarray, g_pos: np.ndarray) -> None:
        """Change only the constant terms of the given rows (second-order correction)."""
        self.uba[row] = -g_pos

    def solve(self, deadline: float = math.inf) -> tuple[np.ndarray, np.ndarray, bool]:
        """Solve the QP: ``(z, row multipliers >= 0, success)``.

        ``deadline`` (a ``time.perf_counter()`` value, the solve's end): every call below
        gets its iteration or time limit from the time left until then, and none is made
        once it has passed (:class:`~controllers.solvers.fast.qp.budget.QPBudget`; the
        calls refused are counted in ``budget.refused``).

        A failed attempt is retried by the elastic interior point (when it is not the
        solver that failed and a C compiler works: measured on the quadrotor's one
        ``QP_Failed`` solve, it solved the QP that qpOASES hot and cold and three qrqp
        calls failed on, in milliseconds instead of 2.9-4.4 s), then by the same with a
        proximal term on the step of ``1e-8``, then ``1e-4``, times the largest Hessian
        diagonal entry (as the compiled loop retries), then by qpOASES cold (a fresh
        memory) and by qrqp, each without and with those proximal terms (degenerate QPs).
        The arrays of the problem are left as they were.
        """
        self.budget.deadline = deadline
        ok = self._attempt(self.solver)
        if ok or not self.elastic:  # (a hard QP may well be infeasible: no retries)
            return self.x.copy(), np.maximum(self.lam_a, 0.0), ok
        self.failures += 1
        ipm = _available("elastic_ipm")
        if self.solver != "elastic_ipm" and ipm:
            self.retried_with_ipm += 1
        retries = [("elastic_ipm", 0.0)] if self.solver != "elastic_ipm" and ipm else []
        retries += [("elastic_ipm", p) for p in PROXIMAL_STEPS[1:] if ipm]
        retries += [(solver, p) for p in PROXIMAL_STEPS for solver in ("qpoases", "qrqp")]
        for solver, prox in retries:
            if self.budget.remaining() <= 0.0:
                break
            if self._retry(solver, prox):
                return self.x.copy(), np.maximum(self.lam_a, 0.0), True
        return self.x.copy(), np.maximum(self.lam_a, 0.0), False

    def _retry(self, solver: str, prox: float) -> bool:
        """One retry of a failed QP by ``solver`` (qpOASES from a fresh memory) with
        ``prox`` times the largest Hessian diagonal entry added to the step's diagonal."""
        nu = self.n_u
        idx = np.arange(nu)
        diag = self.H[idx, idx].copy()
        self.H[idx, idx] = diag + prox * max(float(np.max(np.abs(diag))), 1.0)
        try:
            if solver == "qpoases":
                self._fresh_memory()
            return self._attempt(solver)
        finally:
            self.H[idx, idx] = diag

    def _attempt(self, solver: str) -> bool:
        """One call of ``solver`` on the current arrays; True on success."""
        if solver == "daqp":
            return self._solve_daqp()
        if solver == "piqp":
            return self._solve_piqp()
        if solver == "elastic_ipm":
            return self._solve_elastic_ipm()
        if solver == "qrqp":
            return self._solve_qrqp()
        return self._solve_qpoases()

    def _solve_qpoases(self) -> bool:
        """qpOASES on every slot, hot-started when it can, with at most the working-set
        changes the time left allows."""
        nwsr = self.budget.iterations("qpoases", self.n_var, self.capacity, self._nwsr_default)
        if nwsr < 1:
            self._stale = True
            self.x[:] = np.nan
            self.lam_a[:] = 0.0
            return False
        if nwsr < self._nwsr or nwsr > 1.25 * self._nwsr:  # another limit: another conic
            self._nwsr = nwsr
            self._build_conic()
        if self._stale and self._hot:
            self._fresh_memory()
        self._stale, self._hot = False, True
        t0 = time.perf_counter()
        self._evaluate()
        ok = self._buffer.ret() == 0 and bool(np.isfinite(self.x).all())
        if not ok:  # (then it has usually spent its nWSR: learn their cost)
            self.budget.record("qpoases", self.n_var, self.capacity, time.perf_counter() - t0, nwsr)
        # qpOASES cannot hot-start from a QP it failed on: the next call starts afresh.
        self._stale = not ok
        return ok


__all__ = [
    "AUTO_PIQP_VARIABLES",
    "DAQP_PRIMAL_TOL",
    "INF_BOUND",
    "PIQP_EPS_ABS",
    "PIQP_EPS_REL",
    "QP_SOLVERS",
    "SlotQP",
    "_daqp_time_limit",
    "resolve_qp_solver",
]
