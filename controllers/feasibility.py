"""Can any input satisfy the scenarios? The least slack of the shared linear constraints.

A scenario problem shares one input sequence between all scenarios. Some constraints are
affine in the inputs with the same coefficients in every scenario (their condensed
Jacobian is one constant row per step, found symbolically from the system definition;
the bicycle's speed bounds: ``v_k = v_0 + dt sum(a + w)``). Such a constraint moves every
scenario by the same amount when the inputs change, so the spread between scenarios is
fixed by the data (initial states, latent forces): when the scenarios' speeds at a step
spread wider than the speed band, no input keeps all of them inside, and the slack of that
step's two bounds cannot fall below the excess.

:func:`shared_slack_bound` computes the least total slack of these constraints over every
input sequence within the input bounds, exactly, as a small linear program (HiGHS through
:func:`scipy.optimize.linprog`). It is a lower bound on the total slack of any plan:

* ``> 0``: the problem is infeasible for every input; its optimum keeps at least this much
  slack, and the exact penalty on it dominates the objective (at the paper's penalty of
  1e4 per unit of slack). A long horizon with a strong latent force does this: the
  open-loop spread of the scenarios grows with the horizon.
* ``0``: no verdict (the other constraints may still be unsatisfiable).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linprog

from controllers.problem import ScenarioProblem
from controllers.solvers.fast.screening import shared_linear_constraints

# Least slack [constraint units] above which a problem counts as infeasible for every
# input (the LP's feasibility tolerance is 1e-7).
INFEASIBLE_TOL = 1e-6


@dataclass(frozen=True)
class SharedConstraints:
    """The constraints of a problem that are one exact linear row per step.

    Attributes:
        indices: ``(nL,)`` their indices among the system's constraints.
        rows: ``(nL, N, N nu)`` ``d g_j(x_k) / d u`` (constant).
    """

    indices: np.ndarray
    rows: np.ndarray

    @classmethod
    def of(cls, problem: ScenarioProblem) -> SharedConstraints:
        """Find them from the system's CasADi expressions (symbolic, once per problem)."""
        indices, rows = shared_linear_constraints(problem)
        return cls(indices=indices, rows=rows)


@dataclass(frozen=True)
class SlackBound:
    """The least slack of the shared linear constraints over every input in the bounds.

    Attributes:
        total: the least total slack, summed over steps and constraints, in the
            constraints' units (the bicycle: m/s).
        slack: ``(N, ng)`` the slacks at the LP's optimum (zero for constraints the bound
            does not cover).
        u: ``(N, nu)`` an input sequence attaining it.
        constraints: indices of the constraints it covers.
    """

    total: float
    slack: np.ndarray
    u: np.ndarray
    constraints: np.ndarray

    @property
    def infeasible(self) -> bool:
        """No input satisfies every scenario (``total > INFEASIBLE_TOL``)."""
        return self.total > INFEASIBLE_TOL


def shared_slack_bound(
    problem: ScenarioProblem,
    x0: np.ndarray,
    W: np.ndarray,
    backoff: np.ndarray | None = None,
    shared: SharedConstraints | None = None,
) -> SlackBound:
    """The least total slack of the shared linear constraints, over every input.

    Args:
        problem: the scenario problem.
        x0: initial state ``(nx,)`` or ``(Ns, nx)``.
        W: latent forces ``(Ns, N, nw)`` (or ``(Ns, N)``).
        backoff: constraint tightening as in :meth:`ScenarioProblem.constraint_values`.
        shared: :meth:`SharedConstraints.of` the problem, to reuse over many calls.

    Returns:
        The bound (a zero bound when the problem has no shared linear constraint).

    Raises:
        ValueError: on wrongly shaped data (:meth:`ScenarioProblem.check_data`), or when
            the linear program fails (it is always feasible: slack can absorb anything).
    """
    shared = SharedConstraints.of(problem) if shared is None else shared
    n, nu, ng = problem.horizon, problem.nu, problem.ng
    lower, upper = np.tile(problem.input_lower, n), np.tile(problem.input_upper, n)
    u0 = np.clip(np.zeros(n * nu), lower, upper)
    n_l = shared.indices.size
    if n_l == 0:
        return SlackBound(0.0, np.zeros((n, ng)), u0.reshape(n, nu), shared.indices)
    X = problem.rollout(x0, W, u0.reshape(n, nu))
    g = problem.constraint_values(X, backoff)[:, :, shared.indices]  # (Ns, N, nL)
    rows = shared.rows.transpose(1, 0, 2)  # (N, nL, N nu)
    # g_j(x_k(u)) = c + rows[k, j] . u exactly; the worst scenario sets each step's slack.
    worst = g.max(axis=0) - rows @ u0  # (N, nL)
    # min sum(s)  s.t.  rows[k, j] . u - s_kj <= -worst_kj,  s >= 0,  lower <= u <= upper
    m = n * n_l
    cost = np.concatenate([np.zeros(n * nu), np.ones(m)])
    a_ub = np.hstack([rows.reshape(m, n * nu), -np.eye(m)])
    bounds = [
        (lo if np.isfinite(lo) else None, hi if np.isfinite(hi) else None)
        for lo, hi in zip(lower, upper, strict=True)
    ] + [(0.0, None)] * m
    res = linprog(cost, A_ub=a_ub, b_ub=-worst.ravel(), bounds=bounds, method="highs")
    if res.status != 0:
        raise ValueError(f"the slack bound's linear program failed: {res.message}")
    u = res.x[: n * nu]
    slack = np.zeros((n, ng))
    slack[:, shared.indices] = np.maximum(worst + rows @ u, 0.0)
    return SlackBound(float(slack.sum()), slack, u.reshape(n, nu), shared.indices)


__all__ = ["INFEASIBLE_TOL", "SharedConstraints", "SlackBound", "shared_slack_bound"]
