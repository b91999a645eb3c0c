"""The scenario MPC problem (paper eq. MPCScen) as a CasADi NLP, for any system.

Both formulations minimise exactly :meth:`controllers.problem.ScenarioProblem.objective`
(the scenario-averaged quadratic cost plus an exact L1 penalty on ``ng N`` shared slacks)
and differ only in how the predicted states enter the NLP:

* ``"multiple_shooting"`` (:func:`build_multiple_shooting`): the textbook formulation. The
  states of every scenario are decision variables, the Euler dynamics are equality
  constraints and every scenario constraint is explicit. Large but very sparse; it is the
  reference.
* ``"condensed"`` (:func:`build_condensed`): single shooting. The only decision variables are
  the shared inputs (``nu N``) and the slacks (``ng N``); each scenario's states are
  expressions of the inputs, so the NLP has ``(nu + ng) N`` variables whatever ``Ns`` is.

The NLPs are built from the problem's model alone: the Euler step
(:meth:`ControlSystem.casadi_step`), the state constraints
(:meth:`ControlSystem.casadi_constraints`, possibly none) and the cost
(:class:`~lfm_env.cost.QuadraticCost`, any PSD weights), with the dimensions
``nx, nu, nw, ng`` of the system; the initial states ``x0`` (``Ns x nx``), the latent forces
``W`` (``Ns x N x nw``) and the back-off are parameters, so one NLP serves every step. The
solvers built on them: :mod:`controllers.solvers.casadi.ipopt` (IPOPT, both formulations) and
:mod:`controllers.solvers.casadi.sqpmethod` (CasADi's ``sqpmethod`` on the condensed one).
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from controllers.problem import ScenarioProblem


@dataclass
class ScenarioNLP:
    """A built scenario NLP: its symbolic definition, bounds, and the layout of its vectors.

    The decision vector is ``[vec(u) (nu N), vec(s) (ng N), states]`` where ``states``
    holds ``x_1..x_N`` of every scenario ordered (step, scenario, component) in the
    multiple-shooting formulation and is empty in the condensed one. The parameter vector
    is ``[x0.ravel() (Ns nx), W.ravel() (Ns N nw)]`` with ``x0`` ``(Ns, nx)`` and ``W``
    ``(Ns, N, nw)`` as :meth:`ScenarioProblem.check_data` returns them. ``x_blocks`` and
    ``g_blocks`` give, for each block of the decision and constraint vectors, its size per
    prediction step; every block is ordered step-major, which is what the warm-start
    shift uses.
    """

    nlp: dict[str, ca.SX]
    lbx: np.ndarray
    ubx: np.ndarray
    lbg: np.ndarray
    ubg: np.ndarray
    x_blocks: tuple[int, ...]
    g_blocks: tuple[int, ...]


@dataclass
class NLPSymbols:
    """The symbols and per-scenario functions both formulations are written with."""

    U: ca.SX  # (nu, N) shared inputs
    S: ca.SX  # (ng, N) shared slacks (0 rows without state constraints)
    X0: ca.SX  # (nx, Ns) initial states, column i for scenario i
    W: ca.SX  # (nw N, Ns) latent forces; rows k nw .. (k+1) nw - 1 act during step k
    B: ca.SX  # (ng, N) constraint back-off (a parameter; zero when not used)
    step: ca.Function  # (nx, Ns), (nu, 1), (nw, Ns) -> (nx, Ns): one Euler step
    constraints: ca.Function | None  # (nx, Ns) -> (ng, Ns); None when ng == 0
    state_cost: ca.Function  # (nx, Ns) -> (1, Ns)
    terminal_cost: ca.Function  # (nx, Ns) -> (1, Ns)

    def forces(self, k: int) -> ca.SX:
        """The forces ``(nw, Ns)`` of every scenario acting during step ``k``."""
        nw = self.W.shape[0] // self.U.shape[1]
        return self.W[k * nw : (k + 1) * nw, :]

    def scenario_constraints(self, X: ca.SX, k: int) -> ca.SX:
        """``g_j(x_k^(i)) + b[k, j] - s[k, j]`` for states ``X`` ``(nx, Ns)`` of step ``k``
        (1-based).

        Column ``i`` is scenario ``i``, so ``vec`` orders the rows (scenario, constraint).
        """
        shift = self.B[:, k - 1] - self.S[:, k - 1]
        return self.constraints(X) + ca.repmat(shift, 1, X.shape[1])


def nlp_symbols(problem: ScenarioProblem, kind: type = ca.SX) -> NLPSymbols:
    """Symbols of both formulations and the per-scenario functions mapped over ``Ns``.

    ``Function.map`` evaluates the one-scenario step, constraints and costs on all columns
    at once (the shared input column is broadcast), so building the NLP costs ``N`` Python
    iterations, not ``N Ns``. With ``kind=ca.MX`` the mapped calls stay calls (a loop in
    generated C code) instead of being expanded into ``Ns`` copies of every expression.
    """
    system, cost = problem.system, problem.cost
    n, ns = problem.horizon, problem.n_scenarios
    nx, nu, nw, ng = problem.nx, problem.nu, problem.nw, problem.ng
    x = ca.SX.sym("x", nx)
    return NLPSymbols(
        U=kind.sym("u", nu, n),
        S=kind.sym("s", ng, n) if ng else kind(0, n),
        X0=kind.sym("x0", nx, ns),
        W=kind.sym("W", nw * n, ns),
        B=kind.sym("b", ng, n) if ng else kind(0, n),
        step=system.casadi_step(problem.dt).map(ns),
        constraints=system.casadi_constraints().map(ns) if ng else None,
        state_cost=ca.Function("state_cost", [x], [cost.state_cost(x)]).map(ns),
        terminal_cost=ca.Function("terminal_cost", [x], [cost.terminal_cost(x)]).map(ns),
    )


def nlp_objective(problem: ScenarioProblem, sym: NLPSymbols, state_costs: ca.SX) -> ca.SX:
    """Scenario average of ``state_costs`` ``(1, Ns)``, plus input cost and slack penalty."""
    inputs = sum(problem.cost.input_cost(sym.U[:, k]) for k in range(problem.horizon))
    f = ca.sum2(state_costs) / problem.n_scenarios + inputs
    if problem.ng:
        f += problem.slack_penalty * ca.sum1(ca.sum2(sym.S))
    return f


def build_condensed(problem: ScenarioProblem, kind: type = ca.SX) -> ScenarioNLP:
    """Single shooting: inputs and slacks are the only decision variables.

    ``kind``: the symbols' type, ``ca.SX`` (expanded expressions, for IPOPT) or ``ca.MX``
    (mapped per-scenario calls kept, compact when compiled).
    """
    n, ns, nu, ng = problem.horizon, problem.n_scenarios, problem.nu, problem.ng
    sym = nlp_symbols(problem, kind)

    # --- dynamics ---
    X = sym.X0
    costs = sym.state_cost(X)
    g = []
    for k in range(n):
        X = sym.step(X, sym.U[:, k], sym.forces(k))
        costs += (sym.terminal_cost if k == n - 1 else sym.state_cost)(X)

        # --- constraints ---
        # g_j(x_k^(i)) - s[k, j] <= 0 for every scenario i.
        if ng:
            g.append(ca.vec(sym.scenario_constraints(X, k + 1)))

    nlp = {
        "x": ca.vertcat(ca.vec(sym.U), ca.vec(sym.S)),
        "p": ca.vertcat(ca.vec(sym.X0), ca.vec(sym.W), ca.vec(sym.B)),
        "f": nlp_objective(problem, sym, costs),
        "g": ca.vertcat(*g) if g else kind(0, 1),
    }
    lbx, ubx = input_and_slack_bounds(problem)
    n_g = n * ns * ng
    return ScenarioNLP(
        nlp=nlp,
        lbx=lbx,
        ubx=ubx,
        lbg=np.full(n_g, -np.inf),
        ubg=np.zeros(n_g),
        x_blocks=(nu, ng),
        g_blocks=(ns * ng,),
    )


def build_multiple_shooting(problem: ScenarioProblem) -> ScenarioNLP:
    """Textbook multiple shooting: all scenario states are variables, dynamics are equalities."""
    n, ns, nx, nu, ng = problem.horizon, problem.n_scenarios, problem.nx, problem.nu, problem.ng
    sym = nlp_symbols(problem)
    # Column k * Ns + i holds x_{k+1} of scenario i.
    X = ca.SX.sym("X", nx, n * ns)

    costs = sym.state_cost(sym.X0)
    g_dyn, g_ineq = [], []
    X_prev = sym.X0
    for k in range(n):
        Xk = X[:, k * ns : (k + 1) * ns]

        # --- dynamics ---
        g_dyn.append(ca.vec(Xk - sym.step(X_prev, sym.U[:, k], sym.forces(k))))

        # --- constraints ---
        if ng:
            g_ineq.append(ca.vec(sym.scenario_constraints(Xk, k + 1)))

        costs += (sym.terminal_cost if k == n - 1 else sym.state_cost)(Xk)
        X_prev = Xk

    nlp = {
        "x": ca.vertcat(ca.vec(sym.U), ca.vec(sym.S), ca.vec(X)),
        "p": ca.vertcat(ca.vec(sym.X0), ca.vec(sym.W), ca.vec(sym.B)),
        "f": nlp_objective(problem, sym, costs),
        "g": ca.vertcat(*g_dyn, *g_ineq),
    }
    lbu, ubu = input_and_slack_bounds(problem)
    n_x = nx * n * ns
    n_dyn, n_ineq = nx * n * ns, ng * n * ns
    return ScenarioNLP(
        nlp=nlp,
        lbx=np.concatenate([lbu, np.full(n_x, -np.inf)]),
        ubx=np.concatenate([ubu, np.full(n_x, np.inf)]),
        lbg=np.concatenate([np.zeros(n_dyn), np.full(n_ineq, -np.inf)]),
        ubg=np.zeros(n_dyn + n_ineq),
        x_blocks=(nu, ng, nx * ns),
        g_blocks=(nx * ns, ng * ns),
    )


def input_and_slack_bounds(problem: ScenarioProblem) -> tuple[np.ndarray, np.ndarray]:
    """Bounds of ``[vec(u), vec(s)]``: hard input bounds, slacks in ``[0, inf)``."""
    n, ng = problem.horizon, problem.ng
    lbx = np.concatenate([np.tile(problem.input_lower, n), np.zeros(ng * n)])
    ubx = np.concatenate([np.tile(problem.input_upper, n), np.full(ng * n, np.inf)])
    return lbx, ubx


def shift_blocks(v: np.ndarray, blocks: tuple[int, ...], horizon: int) -> np.ndarray:
    """Shift every step-major block of ``v`` by one prediction step, repeating the last step."""
    out, start = [], 0
    for size in blocks:
        b = v[start : start + size * horizon].reshape(horizon, size)
        out.append(np.concatenate([b[1:], b[-1:]]).ravel())
        start += size * horizon
    return np.concatenate(out)


__all__ = [
    "NLPSymbols",
    "ScenarioNLP",
    "build_condensed",
    "build_multiple_shooting",
    "input_and_slack_bounds",
    "nlp_objective",
    "nlp_symbols",
    "shift_blocks",
]
