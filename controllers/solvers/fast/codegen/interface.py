"""The compiled SQP loop's interface, defined once: its options, statuses and statistics.

The C loop (``codegen/c/sqp.c``), its ctypes face (:mod:`controllers.solvers.fast.compiled`)
and the exported controller (:mod:`controllers.export`) all read these three tables:

* :data:`OPTIONS`: the fields of the C struct ``lfm_sqp_options``, in order, each with its C
  type and how its value comes from
  :class:`~controllers.solvers.fast.options.FastSolverOptions` (a field of the same name, or
  a choice mapped to a number);
* :data:`STATUSES`: the C loop's return codes (``SQ_*``) and the Python loop's status names;
* :data:`STATS`: the statistics ``lfm_sqp_solve`` writes (``ST_*``), in order.

:func:`header` writes the C of all three (the struct and two enums, ``sqp_interface.h``,
included by ``sqp.h``; :func:`~controllers.solvers.fast.codegen.source.c_source` inserts it),
and :class:`SqpOptions` is the ctypes mirror of the struct, built from the same table, so
the two cannot drift apart; the tests compare both with what the compiled library reports
(its ``sizeof``, the counts of statuses and statistics) and check that every
``FastSolverOptions`` field is either here or named in :data:`PYTHON_ONLY`.
"""

from __future__ import annotations

import ctypes
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

# The choices of FastSolverOptions.hessian_modification, by their C code (options.py
# HESSIAN_MODIFICATIONS in order).
HESSIAN_MODIFICATION_CODES = {"floor": 0, "abs": 1, "augmented": 2}
# FastSolverOptions.elastic_qp, by their C code.
ELASTIC_CODES = {"always": 0, "on_demand": 1, "carried": 2}
# FastSolverOptions.feedback_bounds, by their C code.
FEEDBACK_BOUNDS_CODES = {"first": 0, "all": 1}


@dataclass(frozen=True)
class COption:
    """One field of ``lfm_sqp_options``.

    Attributes:
        name: the C field's name (also the ctypes field's).
        kind: ``"long"`` or ``"double"``.
        doc: what it is (the header's comment).
        value: the C value from a ``FastSolverOptions``; ``None``: its field of this name.
    """

    name: str
    kind: str
    doc: str
    value: Callable[[Any], float | int] | None = None

    def of(self, options: Any) -> float | int:
        """This field's value for ``options`` (a ``FastSolverOptions``)."""
        raw = getattr(options, self.name) if self.value is None else self.value(options)
        return float(raw) if self.kind == "double" else int(raw)


def _restart(name: str) -> Callable[[Any], int]:
    return lambda o: int(name in o.restarts)


OPTIONS: tuple[COption, ...] = (
    COption("max_iter", "long", "SQP iterations per start"),
    COption("tol", "double", "predicted merit decrease (relative) that counts as converged"),
    COption("acceptable_tol", "double", "merit decrease (relative) of a stagnating step"),
    COption("acceptable_iter", "long", "stagnating steps in a row that end a start"),
    COption("step_tol", "double", "input step that counts as converged"),
    COption("final_step_tol", "double", "predicted next step that counts as converged"),
    COption("screen_margin", "double", "rows within this of activity enter the QP at once"),
    COption("screen_rows", "long", "scenario rows per group screened or added per round"),
    COption("add_tol", "double", "linearised violation of a missing row that adds it"),
    COption("max_qp_rounds", "long", "check-and-add rounds per SQP iteration"),
    COption("armijo", "double", "sufficient-decrease fraction"),
    COption("backtrack", "double", "line-search shrink factor"),
    COption("min_step", "double", "smallest line-search step"),
    COption("hessian_floor", "double", "smallest Hessian eigenvalue"),
    COption("slack_regularisation", "double", "quadratic weight on the QP slacks"),
    COption(
        "second_order_correction",
        "long",
        "1: second-order correction against the Maratos effect",
        lambda o: int(o.second_order_correction),
    ),
    COption("soc_below_ratio", "double", "accepted-step ratio below which a SOC is tried"),
    COption("damping_init", "double", "first Levenberg-Marquardt damping (trust_radius = 0)"),
    COption("damping_threshold", "double", "line-search step below which the damping grows"),
    COption("damping_decrease", "double", "factor on the damping after a full step"),
    COption(
        "hessian_modification",
        "long",
        '0 "floor", 1 "abs", 2 "augmented"',
        lambda o: HESSIAN_MODIFICATION_CODES[o.hessian_modification],
    ),
    COption(
        "elastic_on_demand",
        "long",
        'elastic_qp: 0 "always", 1 "on_demand", 2 "carried"',
        lambda o: ELASTIC_CODES[o.elastic_qp],
    ),
    COption("max_expand", "long", "doublings of a good full step"),
    COption("expand_ratio", "double", "decrease ratio that allows an expansion"),
    COption("restart_mirror", "long", '"mirror" in restarts', _restart("mirror")),
    COption("restart_straight", "long", '"straight" in restarts', _restart("straight")),
    COption("restart_threshold", "double", "fraction of a mirrored input's bound"),
    COption("restart_probe", "long", "iterations before an extra start may be given up"),
    COption("restart_optimism", "double", "multiple of the promised decrease"),
    COption("restart_margin", "double", "relative margin an extra start must beat"),
    COption("restart_same_tol", "double", "an extra start this close to the best: same"),
    COption("restart_near_tol", "double", "an extra start this close and returning: same"),
    COption("trust_radius", "double", "initial box trust region (fraction of the range)"),
    COption("min_trust_radius", "double", "smallest trust radius"),
    COption("threads", "long", "threads of the rollouts, linearisations, Hessians"),
    COption("max_time", "double", "[s] per solve; INFINITY: none"),
    COption(
        "feedback_bounds",
        "long",
        'feedback problems: 0 "first" (v_0 bounded, v_k free), 1 "all"',
        lambda o: FEEDBACK_BOUNDS_CODES[o.feedback_bounds],
    ),
)

# FastSolverOptions fields that are no C field of their own: the QP solver (the C loop has its
# own), the choices the C fields above map (restarts, elastic_qp), and the trust radius of a
# limited solve (set as trust_radius for that solve).
PYTHON_ONLY = frozenset(
    {"qp_solver", "restarts", "elastic_qp", "rti_trust_radius", "rti_screen_rows"}
)

# The C loop's return codes (sqp.c), in order: (C constant, the Python loop's status name).
STATUSES: tuple[tuple[str, str], ...] = (
    ("SQ_SUCCEEDED", "Solve_Succeeded"),
    ("SQ_ACCEPTABLE", "Solved_To_Acceptable_Level"),
    ("SQ_MAX_ITER", "Maximum_Iterations_Exceeded"),
    ("SQ_WALL_TIME", "Maximum_WallTime_Exceeded"),
    ("SQ_INVALID_START", "Invalid_Initial_Point"),
    ("SQ_INVALID_DERIVATIVES", "Invalid_Derivatives"),
    ("SQ_NUMERICAL_ERROR", "Numerical_Error"),
    ("SQ_QP_FAILED", "QP_Failed"),
    ("SQ_LINE_SEARCH_FAILED", "Line_Search_Failed"),
    ("SQ_ABANDONED", "Abandoned"),
    ("SQ_DUPLICATE", "Duplicate"),
    ("SQ_OUT_OF_MEMORY", "Out_Of_Memory"),
)

# The statistics lfm_sqp_solve writes, in order: (C constant, name in Python, what).
STATS: tuple[tuple[str, str, str], ...] = (
    ("ST_MERIT", "merit", "the plan's merit"),
    ("ST_SLACK", "slack", "its slack"),
    ("ST_ITERATIONS", "iterations", "SQP iterations of every start"),
    ("ST_QP_SOLVES", "qp_solves", "QP solves"),
    ("ST_QP_HARD", "qp_hard", "of them without slacks"),
    ("ST_QP_HARD_REJECTED", "qp_hard_rejected", "QPs without slacks rejected"),
    ("ST_QP_ROWS", "qp_rows", "the most scenario rows of a QP"),
    ("ST_QP_RETRIES", "qp_retries", "QP calls retried"),
    ("ST_QP_ROUNDS_EXHAUSTED", "qp_rounds_exhausted", "iterations out of check-and-add rounds"),
    ("ST_SOC_STEPS", "soc_steps", "second-order corrections kept"),
    ("ST_MERIT_EVALS", "merit_evals", "rollouts"),
    ("ST_FIRST_STATUS", "first_status", "the first start's status"),
    ("ST_FIRST_ITERATIONS", "first_iterations", "its iterations"),
    ("ST_RESTART_MIRROR", "restart_mirror", "the mirror start: -1 not tried, 99 kept, 100 no time"),
    ("ST_RESTART_STRAIGHT", "restart_straight", "the straight start, likewise"),
    ("ST_QP_ELASTIC", "qp_elastic", "elastic interior-point calls"),
    ("ST_START_MERIT", "start_merit", "the warm start's merit"),
    ("ST_START_SLACK", "start_slack", "the warm start's slack"),
    ("ST_LAW_SOURCE", "law_source", "feedback: 0 given, 1 u_guess, 2 previous plan, 3 open loop"),
    ("ST_REFERENCE_ITERATIONS", "reference_iterations", "feedback: the reference solve's"),
    ("ST_REFERENCE_STATUS", "reference_status", "feedback: its status (-1: none)"),
    ("ST_REFERENCE_TIME", "reference_time", "feedback: [s] the reference solve's"),
    ("ST_GAIN_TIME", "gain_time", "feedback: [s] computing the law"),
    ("ST_INPUT_SLACK", "input_slack", "feedback: the input rows' slack"),
    ("ST_TIME_ROLLOUT", "time_rollout", "[s] in rollouts and merits"),
    ("ST_TIME_LINEARISE", "time_linearise", "[s] in linearisations (S, Jg, gradient)"),
    ("ST_TIME_HESSIAN", "time_hessian", "[s] in exact Hessians"),
    ("ST_TIME_CONVEXIFY", "time_convexify", "[s] in convexifications"),
    ("ST_TIME_QP", "time_qp", "[s] in QP solvers"),
    ("ST_TIME_ROWS", "time_rows", "[s] in the row selection and the rows' Jacobians"),
    ("ST_QP_IPM_ITERATIONS", "qp_ipm_iterations", "the elastic interior point's iterations"),
)
# The first statistics summed over the starts (ST_QP_ROWS: the largest).
SUMMED_STATS = 11


def _ctype(kind: str) -> type:
    return {"long": ctypes.c_long, "double": ctypes.c_double}[kind]


class SqpOptions(ctypes.Structure):
    """``lfm_sqp_options`` (:data:`OPTIONS`, field by field)."""

    _fields_ = [(o.name, _ctype(o.kind)) for o in OPTIONS]


def c_options(options: Any) -> SqpOptions:
    """The C loop's options from a ``FastSolverOptions`` (:data:`OPTIONS`)."""
    return SqpOptions(**{o.name: o.of(options) for o in OPTIONS})


def header() -> str:
    """``sqp_interface.h``: the C of :data:`OPTIONS`, :data:`STATUSES` and :data:`STATS`."""
    lines = [
        "/* sqp_interface.h: written by controllers/solvers/fast/codegen/interface.py from its",
        "   tables (the options, statuses and statistics of the compiled SQP loop); the ctypes",
        "   face is built from the same tables. Do not edit. */",
        "#ifndef LFM_SQP_INTERFACE_H",
        "#define LFM_SQP_INTERFACE_H",
        "",
        "#include <string.h>",
        "",
        "/* FastSolverOptions, one field each (bools and choices as longs). */",
        "typedef struct {",
        *(f"  {o.kind} {o.name}; /* {o.doc} */" for o in OPTIONS),
        "} lfm_sqp_options;",
        "",
        "/* The statuses lfm_sqp_solve returns (the Python loop's names: compiled.STATUSES). */",
        "enum {",
        *(f"  {c}, /* {name} */" for c, name in STATUSES),
        "  SQ_COUNT",
        "};",
        "/* Their names, by code (an initialiser of a const char* array). */",
        "#define LFM_SQP_STATUS_NAMES \\",
        "  { \\",
        *(f'    "{name}", \\' for _, name in STATUSES),
        "  }",
        "",
        "/* The statistics lfm_sqp_solve writes, in order (compiled.STATS). */",
        "enum {",
        *(f"  {c}, /* {what} */" for c, _, what in STATS),
        "  ST_COUNT",
        "};",
        f"#define ST_STATS {SUMMED_STATS} /* the first entries summed over the starts */",
        "",
        "/* An option by its name (as acados' options_set): 0, or -1 for an unknown name. */",
        "static inline int lfm_sqp_options_set(lfm_sqp_options* o, const char* name,",
        "                                      double value) {",
        *(
            f'  if (!strcmp(name, "{o.name}")) return o->{o.name} = ({o.kind})value, 0;'
            for o in OPTIONS
        ),
        "  return -1;",
        "}",
        "",
        "#endif",
        "",
    ]
    return "\n".join(lines)


__all__ = [
    "FEEDBACK_BOUNDS_CODES",
    "HESSIAN_MODIFICATION_CODES",
    "OPTIONS",
    "PYTHON_ONLY",
    "STATS",
    "STATUSES",
    "SUMMED_STATS",
    "COption",
    "SqpOptions",
    "c_options",
    "header",
]
