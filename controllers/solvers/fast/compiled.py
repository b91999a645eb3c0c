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

from controllers.problem import MPCSolution, ScenarioProblem, is_usable
from controllers.solvers.fast.codegen.build import CodegenUnavailable, address, load_library
from controllers.solvers.fast.codegen.source import (
    c_source,
    constraint_jacobian_pattern,
    library_source,
)
from controllers.solvers.fast.options import FastSolverOptions
from controllers.solvers.fast.screening import shared_linear_constraints

# The statuses of sqp.c (its enum), by code.
STATUSES = (
    "Solve_Succeeded",
    "Solved_To_Acceptable_Level",
    "Maximum_Iterations_Exceeded",
    "Maximum_WallTime_Exceeded",
    "Invalid_Initial_Point",
    "Invalid_Derivatives",
    "Numerical_Error",
    "QP_Failed",
    "Line_Search_Failed",
    "Abandoned",
    "Duplicate",
    "Out_Of_Memory",
)
SUCCESS = ("Solve_Succeeded", "Solved_To_Acceptable_Level")
# The statistics lfm_sqp_solve writes, in order (sqp.c's ST_ enum).
STATS = (
    "merit",
    "slack",
    "iterations",
    "qp_solves",
    "qp_hard",
    "qp_hard_rejected",
    "qp_rows",
    "qp_retries",
    "qp_rounds_exhausted",
    "soc_steps",
    "merit_evals",
    "first_status",
    "first_iterations",
    "restart_mirror",
    "restart_straight",
    "qp_elastic",
    "start_merit",
)
# The C loop's QP solvers: the only choices it has (the others are Python packages).
C_QP_SOLVERS = ("auto", "elastic_ipm")
FALLBACK_NOTICE = "fast_c: no C library ({reason}); using the Python SQP loop"


class SqpOptions(ctypes.Structure):
    """``lfm_sqp_options`` of sqp.c: :class:`FastSolverOptions` field by field."""

    _fields_ = [
        ("max_iter", ctypes.c_long),
        ("tol", ctypes.c_double),
        ("acceptable_tol", ctypes.c_double),
        ("acceptable_iter", ctypes.c_long),
        ("step_tol", ctypes.c_double),
        ("final_step_tol", ctypes.c_double),
        ("screen_margin", ctypes.c_double),
        ("screen_rows", ctypes.c_long),
        ("add_tol", ctypes.c_double),
        ("max_qp_rounds", ctypes.c_long),
        ("armijo", ctypes.c_double),
        ("backtrack", ctypes.c_double),
        ("min_step", ctypes.c_double),
        ("hessian_floor", ctypes.c_double),
        ("slack_regularisation", ctypes.c_double),
        ("second_order_correction", ctypes.c_long),
        ("soc_below_ratio", ctypes.c_double),
        ("damping_init", ctypes.c_double),
        ("damping_threshold", ctypes.c_double),
        ("damping_decrease", ctypes.c_double),
        ("hessian_modification", ctypes.c_long),
        ("elastic_on_demand", ctypes.c_long),
        ("max_expand", ctypes.c_long),
        ("expand_ratio", ctypes.c_double),
        ("restart_mirror", ctypes.c_long),
        ("restart_straight", ctypes.c_long),
        ("restart_threshold", ctypes.c_double),
        ("restart_probe", ctypes.c_long),
        ("restart_optimism", ctypes.c_double),
        ("restart_margin", ctypes.c_double),
        ("restart_same_tol", ctypes.c_double),
        ("restart_near_tol", ctypes.c_double),
        ("trust_radius", ctypes.c_double),
        ("min_trust_radius", ctypes.c_double),
        ("threads", ctypes.c_long),
        ("max_time", ctypes.c_double),
    ]


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


_MODIFICATIONS = {"floor": 0, "abs": 1, "augmented": 2}


def c_options(options: FastSolverOptions) -> SqpOptions:
    """The C loop's options from the Python loop's (``qp_solver`` and ``restarts`` mapped)."""
    values: dict[str, Any] = {}
    for name, kind in SqpOptions._fields_:
        if name == "hessian_modification":
            values[name] = _MODIFICATIONS[options.hessian_modification]
        elif name == "elastic_on_demand":
            values[name] = int(options.elastic_qp == "on_demand")
        elif name in ("restart_mirror", "restart_straight"):
            values[name] = int(name.removeprefix("restart_") in options.restarts)
        elif name == "second_order_correction":
            values[name] = int(options.second_order_correction)
        else:
            value = getattr(options, name)
            values[name] = float(value) if kind is ctypes.c_double else int(value)
    return SqpOptions(**values)


def problem_arrays(problem: ScenarioProblem) -> dict[str, np.ndarray]:
    """The numbers of ``lfm_sqp_problem`` as contiguous arrays (the export writes the same)."""
    system, cost = problem.system, problem.cost
    shared, shared_rows = shared_linear_constraints(problem)
    screened = [j for j in range(problem.ng) if j not in set(shared.tolist())]
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
        "depends": np.ascontiguousarray(constraint_jacobian_pattern(system), dtype=np.uint8),
        "mirror": np.ascontiguousarray(system.mirror_inputs, dtype=np.int64),
    }


def sqp_source(system, dt: float) -> str:
    """The C source of the system's library with the compiled SQP loop (one translation
    unit: the generated functions, the driver, then ``sqp.c`` with its QP solvers)."""
    return library_source(system, dt) + "\n" + c_source("sqp.c")


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
    lib.lfm_sqp_stats_count.restype = L
    if lib.lfm_sqp_stats_count() != len(STATS):
        raise CodegenUnavailable("the compiled SQP loop's statistics do not match STATS")
    return lib


def sqp_library(system, dt: float) -> ctypes.CDLL:
    """The loaded library with the SQP loop of ``system`` at time step ``dt`` (compiled once
    and cached like the C library).

    Raises:
        CodegenUnavailable: no compiler, or the compilation failed.
    """
    return _declare(load_library(sqp_source(system, dt), "lfm_sqp").lib)


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
        if getattr(problem, "prediction", "open_loop") != "open_loop":
            raise ValueError(
                f"fast_c: prediction={problem.prediction!r}: the C loop solves open-loop "
                "problems only (make_solver(problem, 'fast_c') solves a feedback problem "
                "through its open-loop rewrite)"
            )
        self.problem = problem
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
            self._lib = sqp_library(problem.system, problem.dt)
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
    ) -> MPCSolution:
        """The plan for ``x0`` and ``W``: :meth:`FastScenarioSolver.solve`'s arguments and
        result (``extra["loop"]`` says ``"c"``; ``extra["qp_calls"]`` counts the elastic
        interior point's calls and the dual active-set method's, ``"dense_qp"``)."""
        if self._python is not None:
            sol = self._python.solve(x0, W, u_guess=u_guess, backoff=backoff)
            sol.extra["loop"] = "python"
            return sol
        t_start = time.perf_counter()
        problem = self.problem
        x0, W = problem.check_data(x0, W)
        b = problem.check_backoff(backoff)
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
        return self._solution(code, time.perf_counter() - t_start)

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
