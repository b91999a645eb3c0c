"""CasADi's ``sqpmethod`` + qpOASES on the condensed scenario NLP, JIT-compiled.

:class:`SqpMethodScenarioSolver` is the strongest ready-made alternative to the project's fast
solver a user could pick, and the benchmark's SQP anchor (``make_solver(problem,
"sqpmethod")``): the condensed NLP of :func:`controllers.solvers.casadi.nlp.build_condensed` with MX
symbols, solved by CasADi's exact-Hessian SQP with qpOASES for the QPs, its functions compiled
to C. Warm starts and results as for :class:`~controllers.solvers.casadi.ipopt.IpoptScenarioSolver`,
whose ``solve`` it shares.
"""

from __future__ import annotations

import time
from typing import Any

import casadi as ca
import numpy as np

from controllers.problem import MPCSolution, ScenarioProblem
from controllers.solvers.casadi.ipopt import IpoptScenarioSolver, check_max_time
from controllers.solvers.casadi.nlp import build_condensed
from controllers.solvers.quiet import silenced_output

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
            fails with status ``Maximum_WallTime_Exceeded`` and is not usable (its plan came
            too late).
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
        self._nlp = build_condensed(problem, ca.MX)
        self._cold = self._make_solver("sqp", self.ipopt_options)
        self._warm = self._cold if warm_start_duals else None
        self.build_time = time.perf_counter() - t0  # [s], including the compilation
        self._prev = None

    def _make_solver(self, name: str, options: dict[str, Any]) -> ca.Function:
        opts = {**options, "print_time": False, "error_on_fail": False}
        if self.jit:
            opts.update(JIT_OPTIONS)
        with silenced_output():  # qpOASES's banner, printed as its memories are created
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
        status ``Maximum_WallTime_Exceeded`` and ``usable=False``.
        """
        sol = super().solve(x0, W, u_guess=u_guess, backoff=backoff)
        sol.extra["method"] = "sqpmethod"
        if self.max_time is not None and sol.solve_time > self.max_time:
            sol.extra["sqpmethod_status"] = sol.status
            # The plan came after the limit: not usable in time (the agent falls back).
            sol.status, sol.success, sol.usable = WALL_TIME_STATUS, False, False
            self._prev = {**self._prev, "lam_x": None, "lam_g": None}
        return sol


__all__ = ["DEFAULT_SQP_OPTIONS", "JIT_OPTIONS", "WALL_TIME_STATUS", "SqpMethodScenarioSolver"]
