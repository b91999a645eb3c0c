"""The scenario problem written with csnlp's ``ScenarioBasedMpc`` and solved by IPOPT.

An independent formulation of the same NLP as :mod:`controllers.solvers.casadi.ipopt`, built
with csnlp's wrapper from the problem's model alone: the system's Euler step as the
dynamics ``F(x, u, w)``, its state constraints and the quadratic cost, written for one
scenario and copied to all of them by csnlp (``constraint_from_single``,
``minimize_from_single``). It needs the optional ``bench`` extra (``pip install -e
.[bench]``) and is reached as ``make_solver(problem, "csnlp")``.
"""

from __future__ import annotations

import math
import time
from typing import Any

import casadi as ca
import numpy as np

from controllers.problem import MPCSolution, ScenarioProblem, is_usable
from controllers.solvers.casadi.ipopt import DEFAULT_IPOPT_OPTIONS, check_max_time

SHOOTINGS = ("multi", "single")


def _import_csnlp() -> tuple[Any, Any]:
    """``(Nlp, ScenarioBasedMpc)`` from csnlp, or an ImportError saying how to install it."""
    try:
        from csnlp import Nlp
        from csnlp.wrappers import ScenarioBasedMpc
    except ImportError as exc:
        raise ImportError(
            f"the csnlp solver needs csnlp ({exc}); install it with pip install -e .[bench]"
        ) from exc
    return Nlp, ScenarioBasedMpc


class CsnlpScenarioSolver:
    """The scenario problem built with csnlp's ``ScenarioBasedMpc`` and solved by IPOPT.

    The NLP is the textbook one written with csnlp's wrapper: one state trajectory per
    scenario (``shooting="multi"``: all scenario states are variables, csnlp's default),
    one shared input sequence, the latent forces ``W`` as per-scenario disturbance
    parameters ``w__i`` ``(nw, N)``. csnlp's own soft constraints would give every
    scenario its own slack, so the ``ng N`` slacks shared by all scenarios (the convention
    of :mod:`controllers.problem`) are one extra NLP variable ``s`` ``(ng, N)`` that every
    scenario's constraint ``g(x_k^(i)) <= s[:, k]`` refers to. The objective is csnlp's
    scenario average of the single-scenario cost plus the input cost and the exact L1 slack
    penalty, i.e. exactly :meth:`ScenarioProblem.objective`. A system without state
    constraints (``ng == 0``) has neither slacks nor constraints.

    csnlp shares one initial state among scenarios, so ``x0`` must be ``(nx,)`` (or
    ``(Ns, nx)`` with equal rows).

    Args:
        problem: the scenario problem.
        shooting: csnlp's ``"multi"`` (default) or ``"single"`` shooting.
        ipopt_options: IPOPT options (names without the ``ipopt.`` prefix) merged over
            :data:`controllers.solvers.casadi.ipopt.DEFAULT_IPOPT_OPTIONS`.
        max_time: wall-clock limit of one solve [s] (IPOPT's ``max_wall_time``), ``None``
            for none; a solve that reaches it returns ``success=False``.

    Raises:
        ImportError: csnlp is not installed.
        ValueError: ``shooting`` is not one of :data:`SHOOTINGS`.
    """

    def __init__(
        self,
        problem: ScenarioProblem,
        shooting: str = "multi",
        ipopt_options: dict[str, Any] | None = None,
        max_time: float | None = None,
    ) -> None:
        if shooting not in SHOOTINGS:
            raise ValueError(f"shooting={shooting!r}: must be one of {SHOOTINGS}")
        Nlp, ScenarioBasedMpc = _import_csnlp()
        t0 = time.perf_counter()
        self.problem = problem
        self.shooting = shooting
        system, cost = problem.system, problem.cost
        n, ns, nx, nu, nw, ng = (
            problem.horizon,
            problem.n_scenarios,
            problem.nx,
            problem.nu,
            problem.nw,
            problem.ng,
        )
        mpc = ScenarioBasedMpc(Nlp(sym_type="SX"), ns, n, shooting=shooting)

        # --- variables and parameters ---
        # x0 is free of bounds (it is fixed by the parameter); the state constraints are
        # the soft ones below, so no hard state bounds.
        x, _, _ = mpc.state("x", nx, bound_initial=False)
        u, _ = mpc.action(
            "u", nu, lb=problem.input_lower.reshape(nu, 1), ub=problem.input_upper.reshape(nu, 1)
        )
        mpc.disturbance("w", nw)
        s = mpc.nlp.variable("s", (ng, n), lb=0.0)[0] if ng else None
        b = mpc.nlp.parameter("backoff", (ng, n)) if ng else None  # tightening, shared

        # --- dynamics ---
        # Serial map: SX graphs are expanded anyway, and threads would only add noise here.
        mpc.set_nonlinear_dynamics(system.casadi_step(problem.dt), parallelization="serial")

        # --- constraints ---
        if ng:
            g = system.casadi_constraints().map(n)(x[:, 1:])
            # The right-hand side s is not a single-scenario symbol, so csnlp's per-scenario
            # substitution leaves it shared by all scenarios.
            mpc.constraint_from_single("g", g + b, "<=", s)

        # --- objective ---
        f = sum(cost.state_cost(x[:, k]) for k in range(n)) + cost.terminal_cost(x[:, n])
        # Input cost and penalty are the same in every scenario, so csnlp's average keeps them.
        f += sum(cost.input_cost(u[:, k]) for k in range(n))
        if ng:
            f += problem.slack_penalty * ca.sum1(ca.sum2(s))
        mpc.minimize_from_single(f)

        self.ipopt_options = {**DEFAULT_IPOPT_OPTIONS, **(ipopt_options or {})}
        if max_time is not None:
            self.ipopt_options.setdefault("max_wall_time", check_max_time(max_time))
        mpc.init_solver({"ipopt": self.ipopt_options, "print_time": False, "error_on_fail": False})
        self._mpc = mpc
        self._u = u
        self._prev_u: np.ndarray | None = None
        self.build_time = time.perf_counter() - t0  # [s]

    def reset(self) -> None:
        """Forget the warm start: the next solve starts from zero inputs (clipped)."""
        self._prev_u = None

    def solve(
        self,
        x0: np.ndarray,
        W: np.ndarray,
        u_guess: np.ndarray | None = None,
        backoff: np.ndarray | None = None,
    ) -> MPCSolution:
        """Solve for initial state ``x0`` and latent forces ``W``, warm-started like IPOPT's.

        The initial guess is the IPOPT solvers' primal one: the previous inputs shifted by
        one step (zero inputs clipped into the bounds first), the states of their rollout
        and the smallest feasible slacks.

        Args:
            x0: initial state in the states' units, ``(nx,)`` or ``(Ns, nx)`` with equal rows.
            W: latent forces ``(Ns, N, nw)`` (or ``(Ns, N)`` when ``nw == 1``).
            u_guess: initial inputs ``(N, nu)``; by default the previous solution shifted.
            backoff: constraint tightening ``(N, ng)`` or ``(ng,)``, ``>= 0``; ``None`` for
                none.

        Returns:
            The solution; ``u`` is clipped into the input bounds, and ``objective`` and
            ``slack`` are evaluated on it by :class:`ScenarioProblem`. A failed solve does
            not raise: it returns the last iterate with ``success=False`` (``usable`` when
            its objective is below the initial guess's).

        Raises:
            ValueError: on wrong shapes, non-finite data, or scenario-dependent initial states.
        """
        t_start = time.perf_counter()
        problem, n = self.problem, self.problem.horizon
        x0_all, W = problem.check_data(x0, W)
        if not np.all(x0_all == x0_all[0]):
            raise ValueError(
                "x0: csnlp's ScenarioBasedMpc shares one initial state among scenarios; "
                f"give ({problem.nx},) or equal rows"
            )
        x0 = x0_all[0]
        b = problem.check_backoff(backoff)
        if u_guess is not None:
            u0 = problem.check_inputs(u_guess, "u_guess")
        elif self._prev_u is not None:
            u0 = np.concatenate([self._prev_u[1:], self._prev_u[-1:]])
        else:
            u0 = np.zeros((n, problem.nu))
        u0 = problem.system.clip_input(u0)
        X = problem.rollout(x0, W, u0)

        pars: dict[str, np.ndarray] = {"x_0": x0.reshape(-1, 1)}
        vals0: dict[str, np.ndarray] = {"u": u0.T}
        if problem.ng:
            vals0["s"] = problem.minimal_slack(X, b).T
            pars["backoff"] = np.zeros((problem.ng, n)) if b is None else b.T
        for i in range(problem.n_scenarios):
            pars[f"w__{i}"] = W[i].T
            if self.shooting == "multi":
                vals0[f"x__{i}"] = X[i].T

        t0 = time.perf_counter()
        sol = self._mpc.solve(pars=pars, vals0=vals0)
        # Reading one symbol's value is part of getting the answer; sol.vals would
        # substitute every scenario's states too (~0.2 s at Ns = 150).
        u = np.asarray(sol.value(self._u).full(), dtype=float).T
        solve_time = time.perf_counter() - t0

        if not np.all(np.isfinite(u)):
            u = u0
        u = problem.system.clip_input(u)
        self._prev_u = u.copy()
        predicted = problem.rollout(x0, W, u)
        stats = sol.stats
        objective, success = problem.objective(x0, W, u, b), bool(sol.success)
        start = math.nan if success else problem.objective(x0, W, u0, b)
        return MPCSolution(
            u=u,
            objective=objective,
            slack=float(np.sum(problem.minimal_slack(predicted, b))),
            status=str(sol.status),
            success=success,
            solve_time=solve_time,
            iterations=int(stats.get("iter_count", 0)),
            predicted=predicted,
            extra={
                "csnlp_objective": float(sol.f),
                "wall_time_with_setup": time.perf_counter() - t_start,
                "build_time": self.build_time,
                "start_objective": start,
            },
            usable=is_usable(success, objective, start),
        )


__all__ = ["SHOOTINGS", "CsnlpScenarioSolver"]
