"""Iteration and time budgets of single QP calls, from what is left of a solve.

A QP call cannot be interrupted from Python, so each call of the fast SQP's QP solvers gets
limits of its own from the time the solve has left (``deadline - now``): DAQP its time limit
directly; qpOASES (a working-set recalculation limit, ``nWSR``: CasADi's ``CPUtime`` option
was not honoured, 7.4 s on a recorded QP with a limit of 0.1 s), qrqp, PIQP and the elastic
interior point an iteration limit, the time left divided by the seconds one iteration of that
solver takes on a QP of that size. That figure is measured on the object's own earlier
calls; before the first one it comes from :data:`SECONDS_PER_UNIT` (measured on this
project's QPs, then doubled) times the dense work of one iteration (:func:`work_units`).
qpOASES is never assumed faster than that: its first working-set changes are cheap and its
later ones dear (20 changes took 0.39 s, then 393 took 5.6 s, on the QP below). A
call whose budget is less than one iteration (plus the solver's setup) is not made: it
fails at once, and the SQP returns by its limit with its best iterate.

Measured on the QP that stalled a converged feedback solve at N = 30 (316 variables, 872
rows): qrqp 0.75 s per iteration after a 0.76 s setup (its default limit of 1000 iterations
is minutes), qpOASES cold 0.65 ms per working-set change after 45 ms of setup (5940 changes
by default), PIQP 6 ms per iteration (250 by default).
"""

from __future__ import annotations

import math
import time

#: Seconds per unit of :func:`work_units` of one iteration, before a solver's first call.
SECONDS_PER_UNIT = {
    # (n + m)^3: 0.75 s at n + m = 1188 (a sparse QR of the dense KKT matrix)
    "qrqp": 2.0e-9,
    # n (n + m) per working-set change: 0.65 ms at 316 x 1188 cold from 10 changes to 1000,
    # but 12 ms over 3625 changes at 316 x 1340 (the later changes cost more), and 37 ms
    # over 264 changes there on a machine at load 13
    "qpoases": 1.0e-7,
    "piqp": 2.0e-10,  # n^3 + m n^2: 6 ms at n = 316, m = 872
    # n_u^3 + m n_u^2: 10 ms per iteration at n_u = 60, m = 872 on a loaded machine
    "elastic_ipm": 6.0e-9,
}
#: The share of the time left that one call may plan to use: its cost per iteration is an
#: estimate (a loaded machine, qpOASES's dearer late changes), so it plans for half.
PLANNED_SHARE = 0.5
#: Iterations' worth of setup a call costs before its first iteration (qpOASES's
#: initial factorisations: ~45 ms against 0.65 ms per change on the QP above).
SETUP_ITERATIONS = {"qrqp": 1.0, "qpoases": 70.0, "piqp": 2.0, "elastic_ipm": 1.0}


def work_units(solver: str, n_var: int, n_rows: int) -> float:
    """The dense work of one iteration of ``solver`` on ``n_var`` variables and ``n_rows``
    rows (the unit of :data:`SECONDS_PER_UNIT`)."""
    n, m = float(n_var), float(n_rows)
    if solver == "qrqp":
        return (n + m) ** 3
    if solver == "qpoases":
        return n * (n + m)
    return n**3 + m * n**2


class QPBudget:
    """The iteration budgets of one QP object's calls (module docstring)."""

    def __init__(self) -> None:
        self._per_unit: dict[str, float] = {}  # measured seconds per work unit, by solver
        self.deadline = math.inf  # time.perf_counter() value ending the current solve
        self.refused = 0  # calls not made: less than one iteration's time was left

    def remaining(self) -> float:
        """Seconds left until :attr:`deadline` (``inf`` without one)."""
        if math.isinf(self.deadline):
            return math.inf
        return self.deadline - time.perf_counter()

    def seconds_per_iteration(self, solver: str, n_var: int, n_rows: int) -> float:
        """One iteration of ``solver`` on this size: measured, else the prior estimate."""
        unit = self._per_unit.get(solver, SECONDS_PER_UNIT[solver])
        return unit * work_units(solver, n_var, n_rows)

    def iterations(self, solver: str, n_var: int, n_rows: int, most: int) -> int:
        """The iteration limit of the next call: ``most``, or fewer when the time left
        allows fewer; 0 when it allows not even the setup and one iteration (then the call
        is not to be made, and is counted in :attr:`refused`)."""
        left = self.remaining()
        if math.isinf(left):
            return most
        per = self.seconds_per_iteration(solver, n_var, n_rows)
        allowed = PLANNED_SHARE * left / per - SETUP_ITERATIONS[solver] if per > 0 else math.inf
        if allowed < 1.0:
            self.refused += 1
            return 0
        return int(min(most, allowed))

    def record(self, solver: str, n_var: int, n_rows: int, seconds: float, iters: int) -> None:
        """Learn from a call: ``seconds`` of wall time for ``iters`` iterations."""
        units = work_units(solver, n_var, n_rows) * (max(iters, 0) + SETUP_ITERATIONS[solver])
        if units > 0 and seconds > 0:
            measured = seconds / units
            old = self._per_unit.get(solver)
            learned = measured if old is None else 0.5 * (old + measured)
            if solver == "qpoases":  # its later changes cost more: short calls understate
                learned = max(learned, SECONDS_PER_UNIT[solver])
            self._per_unit[solver] = learned


__all__ = ["PLANNED_SHARE", "SECONDS_PER_UNIT", "SETUP_ITERATIONS", "QPBudget", "work_units"]
