"""CasADi + IPOPT solvers of the scenario MPC problem (paper eq. MPCScen), for any system.

Both formulations minimise exactly :meth:`controllers.problem.ScenarioProblem.objective`
(the scenario-averaged quadratic cost plus an exact L1 penalty on ``ng N`` shared slacks)
and differ only in how the predicted states enter the NLP:

* ``"multiple_shooting"``: the textbook formulation. The states of every scenario are
  decision variables, the Euler dynamics are equality constraints and every scenario
  constraint is explicit. Large but very sparse; it is the reference.
* ``"condensed"`` (default): single shooting. The only decision variables are the shared
  inputs (``nu N``) and the slacks (``ng N``); each scenario's states are SX expressions
  of the inputs, so the NLP has ``(nu + ng) N`` variables whatever ``Ns`` is.

The NLPs are built from the problem's model alone: the Euler step
(:meth:`ControlSystem.casadi_step`), the state constraints
(:meth:`ControlSystem.casadi_constraints`, possibly none) and the cost
(:class:`~lfm_env.system.QuadraticCost`, any PSD weights), with the dimensions
``nx, nu, nw, ng`` of the system. Each solver builds its NLP once, with the initial states
``x0`` (``Ns x nx``) and the latent forces ``W`` (``Ns x N x nw``) as parameters, and
re-solves it at every step with a warm start. The module also gives
:func:`campi_garatti_scenarios`, the scenario count of Campi & Garatti (2008).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from numbers import Integral, Real
from typing import Any

import casadi as ca
import numpy as np
from scipy import special

from controllers.problem import MPCSolution, ScenarioProblem

FORMULATIONS = ("condensed", "multiple_shooting")

DEFAULT_IPOPT_OPTIONS: dict[str, Any] = {
    "print_level": 0,
    "sb": "yes",
    "max_iter": 200,
    "tol": 1e-8,
}

# Previous multipliers are reused only after a solve whose total slack was below this.
WARM_DUALS_MAX_SLACK = 1e-6  # [constraint units]

# Used with the previous multipliers: start close to the central path instead of at
# mu = 0.1, and do not push a good iterate far into the interior.
WARM_START_IPOPT_OPTIONS: dict[str, Any] = {
    "warm_start_init_point": "yes",
    "warm_start_bound_push": 1e-6,
    "warm_start_mult_bound_push": 1e-6,
    "mu_init": 1e-4,
}


@dataclass
class _NLP:
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
class _Symbols:
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


def _symbols(problem: ScenarioProblem, kind: type = ca.SX) -> _Symbols:
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
    return _Symbols(
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


def _objective(problem: ScenarioProblem, sym: _Symbols, state_costs: ca.SX) -> ca.SX:
    """Scenario average of ``state_costs`` ``(1, Ns)``, plus input cost and slack penalty."""
    inputs = sum(problem.cost.input_cost(sym.U[:, k]) for k in range(problem.horizon))
    f = ca.sum2(state_costs) / problem.n_scenarios + inputs
    if problem.ng:
        f += problem.slack_penalty * ca.sum1(ca.sum2(sym.S))
    return f


def _build_condensed(problem: ScenarioProblem, kind: type = ca.SX) -> _NLP:
    """Single shooting: inputs and slacks are the only decision variables.

    ``kind``: the symbols' type, ``ca.SX`` (expanded expressions, for IPOPT) or ``ca.MX``
    (mapped per-scenario calls kept, compact when compiled).
    """
    n, ns, nu, ng = problem.horizon, problem.n_scenarios, problem.nu, problem.ng
    sym = _symbols(problem, kind)

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
        "f": _objective(problem, sym, costs),
        "g": ca.vertcat(*g) if g else kind(0, 1),
    }
    lbx, ubx = _input_and_slack_bounds(problem)
    n_g = n * ns * ng
    return _NLP(
        nlp=nlp,
        lbx=lbx,
        ubx=ubx,
        lbg=np.full(n_g, -np.inf),
        ubg=np.zeros(n_g),
        x_blocks=(nu, ng),
        g_blocks=(ns * ng,),
    )


def _build_multiple_shooting(problem: ScenarioProblem) -> _NLP:
    """Textbook multiple shooting: all scenario states are variables, dynamics are equalities."""
    n, ns, nx, nu, ng = problem.horizon, problem.n_scenarios, problem.nx, problem.nu, problem.ng
    sym = _symbols(problem)
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
        "f": _objective(problem, sym, costs),
        "g": ca.vertcat(*g_dyn, *g_ineq),
    }
    lbu, ubu = _input_and_slack_bounds(problem)
    n_x = nx * n * ns
    n_dyn, n_ineq = nx * n * ns, ng * n * ns
    return _NLP(
        nlp=nlp,
        lbx=np.concatenate([lbu, np.full(n_x, -np.inf)]),
        ubx=np.concatenate([ubu, np.full(n_x, np.inf)]),
        lbg=np.concatenate([np.zeros(n_dyn), np.full(n_ineq, -np.inf)]),
        ubg=np.zeros(n_dyn + n_ineq),
        x_blocks=(nu, ng, nx * ns),
        g_blocks=(nx * ns, ng * ns),
    )


def _input_and_slack_bounds(problem: ScenarioProblem) -> tuple[np.ndarray, np.ndarray]:
    """Bounds of ``[vec(u), vec(s)]``: hard input bounds, slacks in ``[0, inf)``."""
    n, ng = problem.horizon, problem.ng
    lbx = np.concatenate([np.tile(problem.input_lower, n), np.zeros(ng * n)])
    ubx = np.concatenate([np.tile(problem.input_upper, n), np.full(ng * n, np.inf)])
    return lbx, ubx


def _shift_blocks(v: np.ndarray, blocks: tuple[int, ...], horizon: int) -> np.ndarray:
    """Shift every step-major block of ``v`` by one prediction step, repeating the last step."""
    out, start = [], 0
    for size in blocks:
        b = v[start : start + size * horizon].reshape(horizon, size)
        out.append(np.concatenate([b[1:], b[-1:]]).ravel())
        start += size * horizon
    return np.concatenate(out)


class IpoptScenarioSolver:
    """IPOPT solver of a :class:`ScenarioProblem`, built once and re-solved every step.

    Every solve starts from a primal guess (``u_guess``, else the previous plan shifted by
    one step) with the slacks at their minimal values for it. A primal guess alone saves
    IPOPT little (measured at N=7, Ns=150: about 31 instead of 30 iterations), because it
    pushes the iterate into the interior and restarts the barrier at ``mu_init = 0.1``. So
    two IPOPT instances share the NLP: a cold one (IPOPT defaults) and a warm one
    (``warm_start_init_point`` and a small ``mu_init``) that also receives the previous
    multipliers, shifted like the plan: about 16 iterations instead of 30 there. The warm
    one is used only after a successful solve that needed no slack; after solves with
    active slacks the warm start cost iterations instead (measured: 54-63 instead of 34),
    since the penalised constraints change their active set with every draw of ``W``.

    Args:
        problem: the scenario problem (model, cost, horizon, scenario count, penalty).
        formulation: ``"condensed"`` (single shooting, default) or ``"multiple_shooting"``
            (the textbook reference).
        ipopt_options: IPOPT options (names without the ``ipopt.`` prefix) merged over
            :data:`DEFAULT_IPOPT_OPTIONS` (and over :data:`WARM_START_IPOPT_OPTIONS` for
            the warm instance).
        warm_start_duals: pass the previous multipliers to the warm instance; with False
            only the primal guess is warm started.
        max_time: wall-clock limit of one solve [s] (IPOPT's ``max_wall_time``), ``None``
            for none; a solve that reaches it returns its last iterate with
            ``success=False`` and status ``Maximum_WallTime_Exceeded``, and is not retried.
    """

    def __init__(
        self,
        problem: ScenarioProblem,
        formulation: str = "condensed",
        ipopt_options: dict[str, Any] | None = None,
        warm_start_duals: bool = True,
        max_time: float | None = None,
    ) -> None:
        if formulation not in FORMULATIONS:
            raise ValueError(f"formulation={formulation!r}: must be one of {FORMULATIONS}")
        self.problem = problem
        self.formulation = formulation
        self.warm_start_duals = warm_start_duals
        user = dict(ipopt_options or {})
        if max_time is not None:
            user.setdefault("max_wall_time", check_max_time(max_time))
        self.ipopt_options = {**DEFAULT_IPOPT_OPTIONS, **user}
        t0 = time.perf_counter()
        build = _build_condensed if formulation == "condensed" else _build_multiple_shooting
        self._nlp = build(problem)
        self._cold = self._make_solver("cold", self.ipopt_options)
        self._warm = None
        if warm_start_duals:
            warm_options = {**DEFAULT_IPOPT_OPTIONS, **WARM_START_IPOPT_OPTIONS, **user}
            self._warm = self._make_solver("warm", warm_options)
        self.build_time = time.perf_counter() - t0  # [s]
        self._prev: dict[str, np.ndarray | None] | None = None

    def _make_solver(self, name: str, ipopt_options: dict[str, Any]) -> ca.Function:
        opts = {"ipopt": ipopt_options, "print_time": False, "error_on_fail": False}
        return ca.nlpsol(f"scenario_mpc_{self.formulation}_{name}", "ipopt", self._nlp.nlp, opts)

    @staticmethod
    def _run(
        solver: ca.Function, args: dict[str, np.ndarray], duals: dict[str, np.ndarray]
    ) -> tuple[dict[str, ca.DM] | None, Exception | None, dict[str, Any], float]:
        """One IPOPT call: result (None on an exception), the exception, stats, wall time [s]."""
        error = None
        t0 = time.perf_counter()
        try:
            result = solver(**args, **duals)
        except RuntimeError as exc:  # e.g. a NaN in an evaluation CasADi refuses to pass on
            result, error = None, exc
        solve_time = time.perf_counter() - t0
        return result, error, solver.stats(), solve_time

    @staticmethod
    def _iterate(result: dict[str, ca.DM] | None, z0: np.ndarray) -> np.ndarray:
        """IPOPT's final decision vector, or the initial guess if there is no finite one."""
        z = z0 if result is None else result["x"].full().ravel()
        return z if np.all(np.isfinite(z)) else z0

    def _objective_of(
        self,
        result: dict[str, ca.DM],
        z0: np.ndarray,
        x0: np.ndarray,
        W: np.ndarray,
        backoff: np.ndarray | None,
    ) -> float:
        problem = self.problem
        u = self._iterate(result, z0)[: problem.nu * problem.horizon].reshape(-1, problem.nu)
        return problem.objective(x0, W, problem.system.clip_input(u), backoff)

    def reset(self) -> None:
        """Forget the warm start: the next solve starts cold from zero inputs (clipped)."""
        self._prev = None

    def _initial_guess(
        self,
        x0: np.ndarray,
        W: np.ndarray,
        u_guess: np.ndarray | None,
        backoff: np.ndarray | None = None,
    ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """Primal start ``[u, s, states]`` and the multipliers to pass (empty when cold).

        The previous multipliers belong to the previous solution, so they are passed only
        when the primal guess is that solution, shifted (the default) or not (``u_guess``
        equal to the previous ``u``: re-solving the same or a nearby problem).
        """
        problem, n, nlp, prev = self.problem, self.problem.horizon, self._nlp, self._prev
        mode = "cold"
        shifted = None if prev is None else np.concatenate([prev["u"][1:], prev["u"][-1:]])
        if u_guess is not None:
            u0 = u_guess = problem.check_inputs(u_guess, "u_guess")
            if prev is not None and np.array_equal(u_guess, prev["u"]):
                mode = "same"
            elif shifted is not None and np.array_equal(u_guess, shifted):
                mode = "shift"
        elif shifted is not None:
            u0, mode = shifted, "shift"
        else:
            u0 = np.zeros((n, problem.nu))
        u0 = problem.system.clip_input(u0)

        duals: dict[str, np.ndarray] = {}
        if self._warm is not None and mode != "cold" and prev["lam_x"] is not None:
            for key, blocks in (("lam_x", nlp.x_blocks), ("lam_g", nlp.g_blocks)):
                lam = prev[key]
                duals[key + "0"] = _shift_blocks(lam, blocks, n) if mode == "shift" else lam

        X = problem.rollout(x0, W, u0)
        parts = [u0.ravel(), problem.minimal_slack(X, backoff).ravel()]
        if self.formulation == "multiple_shooting":
            parts.append(X[:, 1:].transpose(1, 0, 2).ravel())
        return np.concatenate(parts), duals

    def solve(
        self,
        x0: np.ndarray,
        W: np.ndarray,
        u_guess: np.ndarray | None = None,
        backoff: np.ndarray | None = None,
    ) -> MPCSolution:
        """Solve the scenario problem for initial state(s) ``x0`` and latent forces ``W``.

        Args:
            x0: initial state, in the states' units (``system.state_names``), shape
                ``(nx,)`` or ``(Ns, nx)`` (one per scenario).
            W: latent force of each scenario and step, in the force's units, shape
                ``(Ns, N, nw)`` (or ``(Ns, N)`` when ``nw == 1``).
            u_guess: initial input sequence ``(N, nu)`` in the inputs' units; by default
                the previous solution shifted by one step (zero inputs, clipped into the
                bounds, on the first solve).
            backoff: constraint tightening ``(N, ng)`` or ``(ng,)``, ``>= 0``
                (:meth:`ScenarioProblem.check_backoff`); ``None`` for none.

        Returns:
            The solution; ``u`` is clipped into the input bounds, and ``objective`` and
            ``slack`` are :meth:`ScenarioProblem.objective` and the sum of
            :meth:`ScenarioProblem.minimal_slack` evaluated on it, so every solver is compared
            on the same function. A failed solve does not raise: it returns IPOPT's last
            iterate with ``success=False`` and IPOPT's status. A failed warm-started solve
            is retried once cold (``extra["cold_retry"]``); ``solve_time`` and
            ``iterations`` then cover both calls.

        Raises:
            ValueError: on wrongly shaped or non-finite ``x0``, ``W`` or ``u_guess``.
        """
        problem, n, nlp = self.problem, self.problem.horizon, self._nlp
        x0, W = problem.check_data(x0, W)
        b = problem.check_backoff(backoff)
        b_param = np.zeros(problem.ng * n) if b is None else b.ravel()  # (k, j): vec of (ng, N)
        z0, duals = self._initial_guess(x0, W, u_guess, b)
        args = {
            "x0": z0,
            "p": np.concatenate([x0.ravel(), W.ravel(), b_param]),
            "lbx": nlp.lbx,
            "ubx": nlp.ubx,
            "lbg": nlp.lbg,
            "ubg": nlp.ubg,
        }
        result, error, stats_, solve_time = self._run(
            self._warm if duals else self._cold, args, duals
        )
        iterations = _iterations(stats_, error, self.ipopt_options)
        retried = False
        timed_out = stats_.get("return_status") == "Maximum_WallTime_Exceeded"
        if duals and not timed_out and (error is not None or not stats_.get("success", False)):
            # A warm start that fails must not cost the step: retry cold from the same guess,
            # and if that fails too keep whichever iterate has the lower objective.
            warm_run = (result, error, stats_)
            result, error, stats_, more_time = self._run(self._cold, args, {})
            solve_time += more_time
            iterations += _iterations(stats_, error, self.ipopt_options)
            retried = True
            if not (error is None and stats_.get("success", False)) and warm_run[0] is not None:
                warm_obj = self._objective_of(warm_run[0], z0, x0, W, b)
                if result is None or warm_obj < self._objective_of(result, z0, x0, W, b):
                    result, error, stats_ = warm_run

        z = self._iterate(result, z0)
        nu, ng = problem.nu, problem.ng
        u = problem.system.clip_input(z[: nu * n].reshape(n, nu))
        predicted = problem.rollout(x0, W, u)
        slack = float(np.sum(problem.minimal_slack(predicted, b)))
        success = error is None and bool(stats_.get("success", False))
        status = repr(error) if error is not None else str(stats_.get("return_status", "?"))

        # Multipliers of a failed solve are no good start, and neither (measured) are those
        # of a solve with active slacks: the penalised constraints then change their active
        # set with each new draw of W. Keep only the inputs in both cases.
        lam_x = lam_g = None
        if success and slack <= WARM_DUALS_MAX_SLACK:
            lam_x, lam_g = result["lam_x"].full().ravel(), result["lam_g"].full().ravel()
        self._prev = {"u": u, "lam_x": lam_x, "lam_g": lam_g}
        return MPCSolution(
            u=u,
            objective=problem.objective(x0, W, u, b),
            slack=slack,
            status=status,
            success=success,
            solve_time=solve_time,
            iterations=iterations,
            predicted=predicted,
            extra={
                "formulation": self.formulation,
                "warm_started_duals": bool(duals),
                "cold_retry": retried,
                "ipopt_objective": math.nan if result is None else float(result["f"]),
                "slacks": z[nu * n : (nu + ng) * n].reshape(n, ng).copy(),
            },
        )


# CasADi's sqpmethod with qpOASES: the compiled SQP anchor of the benchmark.
DEFAULT_SQP_OPTIONS: dict[str, Any] = {
    "qpsol": "qpoases",
    "qpsol_options": {"printLevel": "none", "error_on_fail": False},
    "max_iter": 100,
    "tol_pr": 1e-8,
    "tol_du": 1e-8,
    "print_header": False,
    "print_iteration": False,
    "print_status": False,
}
# JIT: CasADi writes the NLP's functions (objective, constraints, their derivatives and the
# Lagrangian's Hessian) as C and compiles them with the system's compiler.
JIT_OPTIONS: dict[str, Any] = {
    "jit": True,
    "compiler": "shell",
    "jit_options": {"flags": ["-O2"], "verbose": False},
}
WALL_TIME_STATUS = "Maximum_WallTime_Exceeded"


class SqpMethodScenarioSolver(IpoptScenarioSolver):
    """CasADi's ``sqpmethod`` + qpOASES on the condensed NLP, JIT-compiled: the SQP anchor.

    The NLP is the condensed one of :class:`IpoptScenarioSolver` (built by the same
    function), solved by CasADi's exact-Hessian SQP with qpOASES for the QPs, the
    generated derivatives compiled to C (:data:`JIT_OPTIONS`; needs a C compiler, and the
    build then takes seconds to minutes). Warm starts as for IPOPT: the previous plan
    shifted, and its multipliers when it succeeded without slack; a failed warm-started
    solve is retried once without multipliers.

    Args:
        problem: the scenario problem.
        sqp_options: ``sqpmethod`` options merged over :data:`DEFAULT_SQP_OPTIONS`.
        jit: compile the NLP's functions (default); False evaluates them in CasADi's
            virtual machine.
        warm_start_duals: pass the previous multipliers.
        max_time: wall-clock limit of one solve [s], ``None`` for none. ``sqpmethod`` has no
            time limit of its own, so it is judged after the solve: a solve that took longer
            fails with status ``Maximum_WallTime_Exceeded`` (its plan came too late).
    """

    def __init__(
        self,
        problem: ScenarioProblem,
        sqp_options: dict[str, Any] | None = None,
        jit: bool = True,
        warm_start_duals: bool = True,
        max_time: float | None = None,
    ) -> None:
        # Not IpoptScenarioSolver.__init__: one sqpmethod instance serves cold and warm
        # solves (multipliers are inputs of the call); solve() is inherited.
        self.problem = problem
        self.formulation = "condensed"
        self.warm_start_duals = warm_start_duals
        self.max_time = None if max_time is None else check_max_time(max_time)
        self.jit = bool(jit)
        self.ipopt_options = {**DEFAULT_SQP_OPTIONS, **(sqp_options or {})}  # read by solve()
        t0 = time.perf_counter()
        # MX symbols: the compiled code loops over the scenarios instead of spelling out
        # every scenario's derivatives (the SX form took gcc minutes and gigabytes).
        self._nlp = _build_condensed(problem, ca.MX)
        self._cold = self._make_solver("sqp", self.ipopt_options)
        self._warm = self._cold if warm_start_duals else None
        self.build_time = time.perf_counter() - t0  # [s], including the compilation
        self._prev = None

    def _make_solver(self, name: str, options: dict[str, Any]) -> ca.Function:
        opts = {**options, "print_time": False, "error_on_fail": False}
        if self.jit:
            opts.update(JIT_OPTIONS)
        return ca.nlpsol(f"scenario_mpc_sqpmethod_{name}", "sqpmethod", self._nlp.nlp, opts)

    def solve(
        self,
        x0: np.ndarray,
        W: np.ndarray,
        u_guess: np.ndarray | None = None,
        backoff: np.ndarray | None = None,
    ) -> MPCSolution:
        """Solve as :meth:`IpoptScenarioSolver.solve` does, with ``sqpmethod``.

        ``extra["method"]`` is ``"sqpmethod"``; a solve longer than ``max_time`` fails with
        status ``Maximum_WallTime_Exceeded``.
        """
        sol = super().solve(x0, W, u_guess=u_guess, backoff=backoff)
        sol.extra["method"] = "sqpmethod"
        if self.max_time is not None and sol.solve_time > self.max_time:
            sol.extra["sqpmethod_status"] = sol.status
            sol.status, sol.success = WALL_TIME_STATUS, False
            self._prev = {**self._prev, "lam_x": None, "lam_g": None}
        return sol


def check_max_time(max_time: Any) -> float:
    """A solve's wall-clock limit [s] as a float, or ``ValueError`` naming ``max_time``."""
    ok = isinstance(max_time, (int, float)) and not isinstance(max_time, bool)
    if not (ok and math.isfinite(max_time) and max_time > 0):
        raise ValueError(f"max_time={max_time!r}: must be a finite number of seconds > 0")
    return float(max_time)


def _iterations(stats_: dict[str, Any], error: Exception | None, options: dict[str, Any]) -> int:
    """IPOPT's iteration count, 0 when it stopped before iterating (``iter_count`` is garbage)."""
    iterations = int(stats_.get("iter_count", 0))
    if error is not None or not 0 <= iterations <= int(options["max_iter"]):
        return 0
    return iterations


_SOLVER_CACHE: dict[tuple[ScenarioProblem, str], IpoptScenarioSolver] = {}
_SOLVER_CACHE_SIZE = 8  # built solvers kept; each holds two IPOPT instances


def solve_scenario_problem(
    problem: ScenarioProblem,
    x0: np.ndarray,
    W: np.ndarray,
    solver: str = "condensed",
    u_guess: np.ndarray | None = None,
) -> MPCSolution:
    """Solve one scenario problem from a cold start (or from ``u_guess``).

    Solvers are cached per ``(problem, formulation)`` so repeated calls do not rebuild the
    NLP; the cached solver's warm start is reset, so each call is independent.

    Args:
        problem: the problem data.
        x0: initial state(s), ``(nx,)`` or ``(Ns, nx)``, in the states' units.
        W: latent forces ``(Ns, N, nw)`` (or ``(Ns, N)`` when ``nw == 1``).
        solver: ``"condensed"`` or ``"multiple_shooting"``.
        u_guess: optional initial inputs ``(N, nu)``.
    """
    key = (problem, solver)
    if key not in _SOLVER_CACHE:
        if len(_SOLVER_CACHE) >= _SOLVER_CACHE_SIZE:
            _SOLVER_CACHE.clear()
        # Each call starts cold, so the warm-start IPOPT instance would never be used.
        _SOLVER_CACHE[key] = IpoptScenarioSolver(
            problem, formulation=solver, warm_start_duals=False
        )
    ipopt = _SOLVER_CACHE[key]
    ipopt.reset()
    return ipopt.solve(x0, W, u_guess=u_guess)


def _binomial_tail(n_scenarios: int, epsilon: float, n_decision: int) -> float:
    """``sum_{i<d} C(Ns, i) eps^i (1 - eps)^(Ns - i)``, the Campi-Garatti confidence bound."""
    return float(special.bdtr(n_decision - 1, n_scenarios, epsilon))


def campi_garatti_scenarios(epsilon: float, beta: float, n_decision: int) -> int:
    """Smallest scenario count ``Ns`` meeting the Campi & Garatti (2008) bound.

    For a convex scenario program with ``d`` decision variables, ``Ns`` scenarios give a
    solution whose violation probability exceeds ``epsilon`` with probability at most
    ``beta`` when ``sum_{i=0}^{d-1} C(Ns, i) eps^i (1-eps)^(Ns-i) <= beta``.

    Args:
        epsilon: admissible violation probability, in (0, 1).
        beta: confidence parameter, in (0, 1).
        n_decision: number ``d`` of decision variables, an integer >= 1.

    Returns:
        The smallest ``Ns`` satisfying the bound. The guarantee is for convex programs; the
        nonlinear MPC is in general not convex, so for it this is a heuristic (paper, Remark 2).

    Raises:
        ValueError: when an argument is out of range.
    """
    if isinstance(epsilon, bool) or not isinstance(epsilon, Real) or not 0.0 < epsilon < 1.0:
        raise ValueError(f"epsilon={epsilon!r}: must be a number in (0, 1)")
    if isinstance(beta, bool) or not isinstance(beta, Real) or not 0.0 < beta < 1.0:
        raise ValueError(f"beta={beta!r}: must be a number in (0, 1)")
    if isinstance(n_decision, bool) or not isinstance(n_decision, Integral) or n_decision < 1:
        raise ValueError(f"n_decision={n_decision!r}: must be an integer >= 1")
    d = int(n_decision)
    # The tail equals 1 for Ns < d and decreases strictly in Ns, so bracket by doubling and
    # then bisect: lo always fails the bound, hi always meets it.
    lo, hi = d - 1, d
    while _binomial_tail(hi, epsilon, d) > beta:
        lo, hi = hi, 2 * hi
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if _binomial_tail(mid, epsilon, d) <= beta:
            hi = mid
        else:
            lo = mid
    return hi
