"""The fast SQP with its whole loop compiled: one C call per solve (the ``"fast_c"`` solver).

:class:`CompiledScenarioSolver` runs the algorithm of
:class:`~controllers.solvers.fast.solver.FastScenarioSolver` (the same options, the same
iterations, tests and extra starts) inside the system's C library: the loop is
``controllers/solvers/fast/codegen/c/sqp.c``, appended to the generated library
(:func:`~controllers.solvers.fast.codegen.source.library_source`), with the project's own QP
solvers in C (the elastic interior point of ``elastic_ipm.c`` for the QPs with slacks, the
dual active-set method of ``dense.c`` for those without). Python checks the data, calls
``lfm_sqp_solve`` once and packs the :class:`~controllers.problem.MPCSolution`.

Where it differs from the Python loop on purpose (``docs/export.md``): the QP solvers are
always the project's own (``qp_solver`` ``"auto"`` and ``"elastic_ipm"`` both mean them; the
Python loop with ``"auto"`` uses qpOASES below 64 variables and DAQP for the QPs without
slacks), and an elastic QP that fails is retried by the same interior point with a proximal
term (the Python loop retries with qpOASES and qrqp). Without a C compiler the solver is the
Python loop with the same options, after a one-line warning (:data:`FALLBACK_NOTICE`).
"""

from __future__ import annotations

import ctypes
import dataclasses
import functools
import math
import time
import warnings
from typing import Any

import numpy as np

from controllers.feedback_law import FeedbackLaw
from controllers.problem import MPCSolution, ScenarioProblem, is_usable
from controllers.solvers.fast.closed_loop import applied_inputs
from controllers.solvers.fast.codegen import interface
from controllers.solvers.fast.codegen.build import CodegenUnavailable, address, load_library
from controllers.solvers.fast.codegen.interface import SqpOptions, c_options
from controllers.solvers.fast.codegen.source import (
    c_source,
    constraint_jacobian_pattern,
    library_source,
)
from controllers.solvers.fast.options import FastSolverOptions
from controllers.solvers.fast.screening import shared_linear_constraints

# The statuses of sqp.c by code, and the statistics lfm_sqp_solve writes, in order (the
# tables of codegen/interface.py, which also writes the C enums).
STATUSES = tuple(name for _, name in interface.STATUSES)
SUCCESS = ("Solve_Succeeded", "Solved_To_Acceptable_Level")
STATS = tuple(name for _, name, _ in interface.STATS)
# The C loop's QP solvers: the only choices it has (the others are Python packages).
C_QP_SOLVERS = ("auto", "elastic_ipm")
FALLBACK_NOTICE = "fast_c: no C library ({reason}); using the Python SQP loop"
# Where a feedback solve's law came from (the C loop's ST_LAW_SOURCE), by code.
_SOURCES = ("law", "u_guess", "previous_plan", "open_loop_solve")


class SqpProblem(ctypes.Structure):
    """``lfm_sqp_problem`` of sqp.c (pointers into arrays the caller keeps alive)."""

    _fields_ = [
        ("n", ctypes.c_long),
        ("ns", ctypes.c_long),
        ("slack_penalty", ctypes.c_double),
        ("input_lower", ctypes.c_void_p),
        ("input_upper", ctypes.c_void_p),
        ("goal", ctypes.c_void_p),
        ("Q", ctypes.c_void_p),
        ("Qf", ctypes.c_void_p),
        ("R", ctypes.c_void_p),
        ("n_shared", ctypes.c_long),
        ("shared", ctypes.c_void_p),
        ("shared_rows", ctypes.c_void_p),
        ("n_screened", ctypes.c_long),
        ("screened", ctypes.c_void_p),
        ("depends", ctypes.c_void_p),
        ("n_mirror", ctypes.c_long),
        ("mirror", ctypes.c_void_p),
    ]


def problem_arrays(problem: ScenarioProblem) -> dict[str, np.ndarray]:
    """The numbers of ``lfm_sqp_problem`` as contiguous arrays (the export writes the same).

    A feedback problem has no shared rows, and every row type is screened: the state
    constraints and each input's upper and lower row (which depend on no state)."""
    system, cost = problem.system, problem.cost
    depends = constraint_jacobian_pattern(system)
    if problem.prediction == "feedback":
        shared, shared_rows = np.zeros(0, dtype=int), np.zeros((0, problem.horizon, 0))
        depends = np.concatenate([depends, np.zeros((2 * problem.nu, problem.nx), bool)])
    else:
        shared, shared_rows = shared_linear_constraints(problem)
    screened = [j for j in range(depends.shape[0]) if j not in set(shared.tolist())]
    return {
        "input_lower": np.ascontiguousarray(problem.input_lower, dtype=float),
        "input_upper": np.ascontiguousarray(problem.input_upper, dtype=float),
        "goal": np.ascontiguousarray(cost.x_goal, dtype=float),
        "Q": np.ascontiguousarray(cost.Q, dtype=float),
        "Qf": np.ascontiguousarray(cost.Qf, dtype=float),
        "R": np.ascontiguousarray(cost.R, dtype=float),
        "shared": np.ascontiguousarray(shared, dtype=np.int64),
        "shared_rows": np.ascontiguousarray(shared_rows, dtype=float),
        "screened": np.ascontiguousarray(screened, dtype=np.int64),
        "depends": np.ascontiguousarray(depends, dtype=np.uint8),
        "mirror": np.ascontiguousarray(system.mirror_inputs, dtype=np.int64),
    }


def sqp_source(system, dt: float, feedback: bool = False) -> str:
    """The C source of the system's library with the compiled SQP loop (one translation
    unit: the generated functions, the driver, then ``sqp.c`` with its QP solvers); with
    ``feedback`` that of the feedback prediction (``sqp.c`` includes ``feedback.c``)."""
    return library_source(system, dt, feedback) + "\n" + c_source("sqp.c")


@functools.cache
def _declare(lib: ctypes.CDLL) -> ctypes.CDLL:
    P, L = ctypes.c_void_p, ctypes.c_long
    lib.lfm_sqp_new.argtypes = [ctypes.POINTER(SqpProblem), ctypes.POINTER(SqpOptions)]
    lib.lfm_sqp_new.restype = P
    lib.lfm_sqp_free.argtypes = [P]
    lib.lfm_sqp_free.restype = None
    lib.lfm_sqp_reset.argtypes = [P]
    lib.lfm_sqp_reset.restype = None
    lib.lfm_sqp_set_max_time.argtypes = [P, ctypes.c_double]
    lib.lfm_sqp_set_max_time.restype = None
    lib.lfm_sqp_solve.argtypes = [P, P, P, P, P, P, P, P]
    lib.lfm_sqp_solve.restype = ctypes.c_int
    lib.lfm_sqp_set_option.argtypes = [P, ctypes.c_char_p, ctypes.c_double]
    lib.lfm_sqp_set_option.restype = ctypes.c_int
    for name in (
        "lfm_sqp_stats_count",
        "lfm_sqp_status_count",
        "lfm_sqp_options_size",
        "lfm_sqp_feedback",
    ):
        getattr(lib, name).restype = L
    if lib.lfm_sqp_feedback():
        lib.lfm_sqp_set_law.argtypes = [P, P, P]
        lib.lfm_sqp_law.argtypes = [P, P, P, P]
        lib.lfm_sqp_set_law.restype = lib.lfm_sqp_law.restype = ctypes.c_int
    if (
        lib.lfm_sqp_stats_count() != len(STATS)
        or lib.lfm_sqp_status_count() != len(STATUSES)
        or lib.lfm_sqp_options_size() != ctypes.sizeof(SqpOptions)
    ):
        raise CodegenUnavailable(
            "the compiled SQP loop's options, statuses or statistics do not match "
            "codegen/interface.py"
        )
    return lib


def sqp_library(system, dt: float, feedback: bool = False) -> ctypes.CDLL:
    """The loaded library with the SQP loop of ``system`` at time step ``dt`` (compiled once
    and cached like the C library; with ``feedback``, of its feedback prediction).

    Raises:
        CodegenUnavailable: no compiler, or the compilation failed.
    """
    stem = "lfm_sqp_feedback" if feedback else "lfm_sqp"
    return _declare(load_library(sqp_source(system, dt, feedback), stem).lib)


class _Handle:
    """An ``lfm_sqp`` object of the library, freed with this handle."""

    def __init__(self, lib: ctypes.CDLL, problem: SqpProblem, options: SqpOptions) -> None:
        self.lib = lib
        self.ptr = lib.lfm_sqp_new(ctypes.byref(problem), ctypes.byref(options))
        if not self.ptr:
            raise MemoryError("lfm_sqp_new: out of memory")

    def __del__(self) -> None:
        ptr, self.ptr = getattr(self, "ptr", None), None
        if ptr:
            self.lib.lfm_sqp_free(ptr)


class CompiledScenarioSolver:
    """The fast SQP with its loop in C; the face of every solver (``solve``, ``reset``).

    Args:
        problem: the scenario problem.
        **options: fields of :class:`FastSolverOptions`; ``qp_solver`` must be ``"auto"`` or
            ``"elastic_ipm"`` (both: the C loop's own QP solvers).

    Attributes:
        loop: ``"c"``, or ``"python"`` when no C library could be built (the fallback: the
            Python loop, :class:`~controllers.solvers.fast.solver.FastScenarioSolver`, with
            the same options; a one-line :class:`RuntimeWarning` says so).
        fallback_reason: why the fallback was taken (``None`` with the C loop).

    Raises:
        ValueError: on an unknown or out-of-range option, or another ``qp_solver``.
    """

    def __init__(self, problem: ScenarioProblem, **options: Any) -> None:
        unknown = set(options) - set(FastSolverOptions.__dataclass_fields__)
        if unknown:
            raise ValueError(f"unknown {type(self).__name__} options: {sorted(unknown)}")
        self.problem = problem
        self.feedback = problem.prediction == "feedback"
        self.options = FastSolverOptions(**options)
        if self.options.qp_solver not in C_QP_SOLVERS:
            raise ValueError(
                f"fast_c: qp_solver={self.options.qp_solver!r}: must be one of {C_QP_SOLVERS} "
                "(the C loop has its own QP solvers; the Python loop, 'fast', takes the others)"
            )
        self._raw_options = dict(options)
        self.loop = "c"
        self.fallback_reason: str | None = None
        self._python = None
        self._handle: _Handle | None = None
        try:
            self._lib = sqp_library(problem.system, problem.dt, self.feedback)
        except CodegenUnavailable as err:
            self._fall_back(str(err))
        else:
            self._arrays = problem_arrays(problem)
            self._build()

    def _fall_back(self, reason: str) -> None:
        from controllers.solvers.fast.solver import FastScenarioSolver

        self.loop, self.fallback_reason = "python", reason.splitlines()[0] if reason else "?"
        warnings.warn(
            FALLBACK_NOTICE.format(reason=self.fallback_reason), RuntimeWarning, stacklevel=3
        )
        self._python = FastScenarioSolver(self.problem, **self._raw_options)

    def _build(self) -> None:
        p, a = self.problem, self._arrays
        c_problem = SqpProblem(
            n=p.horizon,
            ns=p.n_scenarios,
            slack_penalty=float(p.slack_penalty),
            n_shared=a["shared"].size,
            n_screened=a["screened"].size,
            n_mirror=a["mirror"].size,
            **{k: address_or_none(v) for k, v in a.items()},
        )
        self._handle = _Handle(self._lib, c_problem, c_options(self.options))
        ns, n, nx, nu = p.n_scenarios, p.horizon, p.nx, p.nu
        self._u = np.empty(n * nu)
        self._X = np.empty((n + 1, nx, ns))
        self._stats = np.empty(len(STATS))
        if self.feedback:  # the last solve's law and nominal inputs
            self._K, self._r = np.empty((n, nu, nx)), np.empty((n, nx))
            self._nominal = np.empty((n, nu))

    @property
    def backend(self) -> str:
        """``"compiled-c"`` (the whole loop in C), or the fallback's backend."""
        return "compiled-c" if self._python is None else self._python.backend

    def set_max_time(self, seconds: float) -> None:
        """The wall-clock limit of the next solves [s] (``FastSolverOptions.max_time``)."""
        if seconds == self.options.max_time:
            return
        self.options = dataclasses.replace(self.options, max_time=float(seconds))
        self._raw_options["max_time"] = float(seconds)
        if self._python is not None:
            self._python.set_max_time(seconds)
        elif self._handle is not None:
            self._lib.lfm_sqp_set_max_time(self._handle.ptr, float(seconds))

    def reset(self) -> None:
        """Forget the warm start: the next solve starts from zero inputs."""
        if self._python is not None:
            self._python.reset()
        elif self._handle is not None:
            self._lib.lfm_sqp_reset(self._handle.ptr)

    def __getstate__(self) -> dict[str, Any]:
        return {"problem": self.problem, "options": self._raw_options}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__init__(state["problem"], **state["options"])

    def solve(
        self,
        x0: np.ndarray,
        W: np.ndarray,
        u_guess: np.ndarray | None = None,
        backoff: np.ndarray | None = None,
        law: FeedbackLaw | None = None,
        iterations: int | None = None,
    ) -> MPCSolution:
        """The plan for ``x0`` and ``W``: :meth:`FastScenarioSolver.solve`'s arguments and
        result (``extra["loop"]`` says ``"c"``; ``extra["qp_calls"]`` counts the elastic
        interior point's calls and the dual active-set method's, ``"dense_qp"``). A feedback
        problem's law (given, or from the reference plan) is computed in C as well."""
        if self._python is not None:
            sol = self._python.solve(x0, W, u_guess, backoff, law=law, iterations=iterations)
            sol.extra["loop"] = "python"
            return sol
        limited = self.options.limited(iterations)
        if limited is self.options:
            return self._solve(x0, W, u_guess, backoff, law)
        self._set_options(limited)  # (by name, for this call)
        try:
            return self._solve(x0, W, u_guess, backoff, law)
        finally:
            self._set_options(self.options)

    def _set_options(self, options: FastSolverOptions) -> None:
        """The options of the C solver's next solves: the iteration limit, extra starts and
        trust radius (what :meth:`FastSolverOptions.limited` changes)."""
        values = c_options(options)
        limited = (
            "max_iter",
            "restart_mirror",
            "restart_straight",
            "trust_radius",
            "elastic_on_demand",
            "screen_rows",
        )
        for name in limited:
            code = self._lib.lfm_sqp_set_option(
                self._handle.ptr, name.encode(), float(getattr(values, name))
            )
            if code:
                raise RuntimeError(f"lfm_sqp_set_option: the C loop has no option {name!r}")

    def _solve(
        self,
        x0: np.ndarray,
        W: np.ndarray,
        u_guess: np.ndarray | None,
        backoff: np.ndarray | None,
        law: FeedbackLaw | None,
    ) -> MPCSolution:
        """:meth:`solve` in C with the options set."""
        t_start = time.perf_counter()
        problem = self.problem
        law = problem.check_law(law)
        x0, W = problem.check_data(x0, W)
        b = problem.check_backoff(backoff)
        if law is not None:
            K, r = np.ascontiguousarray(law.K), np.ascontiguousarray(law.r)
            self._lib.lfm_sqp_set_law(self._handle.ptr, address(K), address(r))
        x0c = np.ascontiguousarray(x0, dtype=float)
        Wc = np.ascontiguousarray(W, dtype=float)
        guess = None
        if u_guess is not None:
            guess = np.ascontiguousarray(problem.check_inputs(u_guess, "u_guess"), dtype=float)
        bc = None if b is None else np.ascontiguousarray(b, dtype=float)
        code = self._lib.lfm_sqp_solve(
            self._handle.ptr,
            address(x0c),
            address(Wc),
            address_or_none(guess),
            address_or_none(bc),
            address(self._u),
            address(self._X),
            address(self._stats),
        )
        sol = self._solution(code, time.perf_counter() - t_start)
        return self._feedback_solution(sol, law) if self.feedback else sol

    def _feedback_solution(self, sol: MPCSolution, given: FeedbackLaw | None) -> MPCSolution:
        """A feedback solve's result as the Python loop's (:mod:`.closed_loop`): its law
        (``given``, or the one the C loop computed), nominal inputs and ``extra``."""
        K, r, nominal = self._K, self._r, self._nominal
        self._lib.lfm_sqp_law(self._handle.ptr, address(K), address(r), address(nominal))
        law = given if given is not None else FeedbackLaw(K.copy(), r.copy())
        stats = dict(zip(STATS, self._stats.tolist(), strict=True))
        source = _SOURCES[int(stats["law_source"])]
        reference = None
        if source == "open_loop_solve":
            reference = {
                "status": STATUSES[int(stats["reference_status"])],
                "iterations": int(stats["reference_iterations"]),
                "solve_time": stats["reference_time"],
            }
        sol.law, sol.nominal_u = law, nominal.copy()
        sol.extra.update(
            inputs=applied_inputs(sol.predicted, sol.u, law),
            state_slack=sol.slack - stats["input_slack"],
            input_slack=stats["input_slack"],
            reference=source,
            open_loop=reference,
            gain_time=stats["gain_time"],
        )
        if not np.all(np.isfinite(sol.u)):
            sol.usable = False
        return sol

    def _solution(self, code: int, elapsed: float) -> MPCSolution:
        p = self.problem
        stats = dict(zip(STATS, self._stats.tolist(), strict=True))
        status = STATUSES[code]
        extra: dict[str, Any] = {
            key: int(stats[key])
            for key in (
                "qp_solves",
                "qp_hard",
                "qp_hard_rejected",
                "qp_rows",
                "qp_retries",
                "qp_rounds_exhausted",
                "soc_steps",
                "merit_evals",
            )
        }
        extra["qp_calls"] = {
            "elastic_ipm": int(stats["qp_elastic"]),
            "dense_qp": int(stats["qp_solves"] - stats["qp_elastic"]),
        }
        extra["restarts"] = {}
        for name in ("mirror", "straight"):
            value = int(stats[f"restart_{name}"])
            if value >= 0:
                extra["restarts"][name] = {99: "kept", 100: "no_time"}.get(
                    value, STATUSES[value].lower() if value < len(STATUSES) else "?"
                )
        first = int(stats["first_status"])
        extra["first_start"] = {
            "status": STATUSES[first],
            "iterations": int(stats["first_iterations"]),
        }
        extra.update(
            backend="compiled-c",
            loop="c",
            threads=self.options.threads,
            qp_solver=self.options.qp_solver,
        )
        merit = stats["merit"]
        extra["start_merit"] = stats["start_merit"]  # the warm start's (MPCSolution.usable)
        extra["start_slack"] = stats["start_slack"]
        # [s] where the time went (the C loop's timers)
        extra["time"] = {
            key: stats[f"time_{key}"]
            for key in ("rollout", "linearise", "hessian", "convexify", "qp", "rows")
        }
        extra["qp_ipm_iterations"] = int(stats["qp_ipm_iterations"])
        success = status in SUCCESS
        return MPCSolution(
            u=self._u.reshape(p.horizon, p.nu).copy(),
            objective=merit if math.isfinite(merit) else math.inf,
            slack=stats["slack"],
            status=status,
            success=success,
            solve_time=elapsed,
            iterations=int(stats["iterations"]),
            predicted=np.ascontiguousarray(self._X.transpose(2, 0, 1)),
            extra=extra,
            usable=is_usable(success, merit, stats["start_merit"]),
        )


def address_or_none(a: np.ndarray | None) -> int | None:
    """The data address of a C-contiguous array, ``None`` for ``None`` or an empty array."""
    if a is None or a.size == 0:
        return None
    return address(a)


__all__ = [
    "C_QP_SOLVERS",
    "FALLBACK_NOTICE",
    "STATS",
    "STATUSES",
    "CompiledScenarioSolver",
    "SqpOptions",
    "SqpProblem",
    "c_options",
    "problem_arrays",
    "sqp_library",
    "sqp_source",
]
