"""Which rows enter the fast solver's QP: the shared linear rows, and the NumPy reference of
the scenario rows' selection.

Constraints whose condensed Jacobian is one constant row per step for every scenario
(:func:`shared_linear_constraints`, found symbolically from the system; the bicycle's speed
bounds) enter as one exact row per step, for the extreme scenario. For the others, the
scenario problem has ``ng N Ns`` scenario rows (constraint ``j``, step ``k``, scenario
``i``); the fast SQP puts only a few of each (constraint, step) *group* into its QP and adds
the rest by check-and-add. Two selections decide which:

* :func:`screen_rows`: the rows a QP starts with, from the rollout's constraint values;
* :func:`worst_rows`: the rows a QP step violates to first order, to add in the next round.

Both pick "the ``keep`` largest values of a group" with a fixed rule for ties (the larger
value first, then the lower scenario index) and return the rows sorted by (constraint
position, step, scenario), so the result is a function of the values alone. The C
library (``lfm_screen``, ``lfm_violated`` in ``controllers/solvers/fast/codegen/c/selection.c``)
implements the same rule and must return the same rows;
:class:`~controllers.solvers.fast.condensed.CondensedModel` picks the implementation.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from controllers.problem import ScenarioProblem


def shared_linear_constraints(problem: ScenarioProblem) -> tuple[np.ndarray, np.ndarray]:
    """Constraints whose condensed Jacobian is one constant row per step, and those rows.

    Returns ``(indices (nL,), rows (nL, N, N nu))``: ``d g_j(x_k) / d u`` does not depend
    on the initial state, the force or ``u`` for ``j`` in ``indices``.
    """
    system, n, dt = problem.system, problem.horizon, problem.dt
    nx, nu, nw, ng = problem.nx, problem.nu, problem.nw, problem.ng
    if ng == 0:
        return np.zeros(0, dtype=int), np.zeros((0, n, n * nu))
    x0, w, U = ca.SX.sym("x0", nx), ca.SX.sym("w", nw, n), ca.SX.sym("u", nu * n)
    step, cons = system.casadi_step(dt), system.casadi_constraints()
    x, G = x0, []
    for k in range(n):
        x = step(x, U[k * nu : (k + 1) * nu], w[:, k])
        G.append(cons(x))
    G = ca.horzcat(*G)  # (ng, N)
    data = ca.vertcat(x0, ca.vec(w), U)
    indices, rows = [], []
    for j in range(ng):
        J = ca.jacobian(ca.vec(G[j, :]), U)  # (N, N nu)
        if not ca.depends_on(J, data):
            indices.append(j)
            zero = ca.Function("J", [data], [J])(np.zeros(data.shape[0]))
            rows.append(np.asarray(ca.densify(zero), dtype=float))
    if not indices:
        return np.zeros(0, dtype=int), np.zeros((0, n, n * nu))
    return np.array(indices), np.stack(rows)


def largest(values: np.ndarray, keep: int) -> np.ndarray:
    """Column indices ``(groups, keep)`` of the ``keep`` largest entries of each row of
    ``values`` ``(groups, Ns)``: larger value first, equal values by lower index."""
    return np.argsort(-values, axis=1, kind="stable")[:, :keep]


def screen_rows(
    G: np.ndarray,
    X: np.ndarray,
    screened: np.ndarray,
    depends: np.ndarray,
    margin: float,
    keep: int,
) -> np.ndarray:
    """Initial scenario rows ``(r, 3)`` of ``(constraint, step index from 0, scenario)``.

    In every (constraint, step) group whose largest value is at least ``-margin``: the
    ``keep`` largest values among those at least ``-margin``, the scenario with the
    smallest value, and the scenarios with the largest and the smallest value of every
    state the constraint depends on at that step (first index on ties).

    Args:
        G: constraint values ``(ng, N, Ns)`` of steps 1..N.
        X: states ``(N + 1, nx, Ns)``.
        screened: the constraints with scenario rows, ascending.
        depends: ``(ng, nx)``, constraint ``j`` depends on state ``m``.
        margin: distance from activity [the constraint's unit] within which rows enter.
        keep: rows per group by value.
    """
    n, ns = G.shape[1], G.shape[2]
    if screened.size == 0:
        return np.empty((0, 3), dtype=int)
    Gs = G[screened].reshape(screened.size * n, ns)
    active = np.nonzero(Gs.max(axis=1) >= -margin)[0]
    if active.size == 0:
        return np.empty((0, 3), dtype=int)
    Ga = Gs[active]
    top = largest(Ga, min(keep, ns))
    sub, col = np.nonzero(np.take_along_axis(Ga, top, axis=1) >= -margin)
    flat = [active[sub] * ns + top[sub, col], active * ns + Ga.argmin(axis=1)]
    step = active % n
    j_of = screened[active // n]
    for state in np.flatnonzero(depends[screened].any(axis=0)):
        users = depends[j_of, state]
        if users.any():
            steps = step[users] + 1  # X holds step 0 too
            flat.append(active[users] * ns + X[steps, state].argmax(axis=1))
            flat.append(active[users] * ns + X[steps, state].argmin(axis=1))
    group, scen = np.divmod(np.unique(np.concatenate(flat)), ns)
    return np.column_stack([screened[group // n], group % n, scen])


def worst_rows(
    viol: np.ndarray, screened: np.ndarray, pos: np.ndarray, tol: float, keep: int
) -> np.ndarray:
    """Scenario rows ``(r, 3)`` not in ``pos`` whose value in ``viol`` exceeds ``tol``:
    up to ``keep`` of the largest per (constraint, step) group.

    Args:
        viol: ``(len(screened), N, Ns)`` linearised constraint values minus the QP's slack
            (overwritten at the rows of ``pos``).
        screened: the constraints of ``viol``'s first axis, ascending.
        pos: rows ``(q, 3)`` already in the QP (their constraints among ``screened``).
        tol: violation above which a row is added [the constraint's unit].
        keep: rows per group.
    """
    n = viol.shape[1]
    where = np.searchsorted(screened, pos[:, 0])
    viol[where, pos[:, 1], pos[:, 2]] = -np.inf
    flat = viol.reshape(screened.size * n, -1)
    bad = np.nonzero(flat.max(axis=1) > tol)[0]
    if bad.size == 0:
        return np.empty((0, 3), dtype=int)
    flat = flat[bad]
    worst = np.sort(largest(flat, min(keep, flat.shape[1])), axis=1)
    sub, col = np.nonzero(np.take_along_axis(flat, worst, axis=1) > tol)
    group = bad[sub]
    return np.column_stack([screened[group // n], group % n, worst[sub, col]])


__all__ = ["largest", "screen_rows", "shared_linear_constraints", "worst_rows"]
