"""Solvers side by side on the same closed-loop problems: times, iterations, objectives.

:func:`time_solvers` builds solvers through the registry, has each solve the problems in
closed-loop order, warm-started from its own past, interleaved in a rotating order (load
changes hit all alike). Every objective is :meth:`~controllers.problem.ScenarioProblem.objective`
of the returned inputs, so objectives compare across formulations; the reference is the
textbook multiple-shooting IPOPT (:data:`REFERENCES` gives the fallbacks).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any

import numpy as np
from tqdm.auto import tqdm

from controllers.problem import ScenarioProblem
from controllers.solvers import SOLVERS, make_solver, solver_spec
from experiments.benchmark.failures import failures_of
from experiments.benchmark.problems import DEFAULT_CONFIG, problem_from_config
from experiments.evaluation.interrupts import raise_if_interrupted

SOLVER_LABELS = {
    "fast": "fast SQP, derivatives generated from the system (FastScenarioSolver)",
    "fast_2threads": "fast SQP, its C library on two threads (threads=2)",
    "fast_c": "fast SQP with its whole loop compiled (CompiledScenarioSolver, own C QP solvers)",
    "ipopt": "IPOPT, condensed (single shooting)",
    "ipopt_multiple_shooting": "IPOPT, multiple shooting, exact Hessian (textbook reference)",
    "sqpmethod": "CasADi sqpmethod + qpOASES, condensed, JIT-compiled (the SQP anchor)",
    "csnlp": "csnlp ScenarioBasedMpc + IPOPT",
}
FAST_SOLVERS = ("fast", "fast_c")  # timed again alone, without IPOPT in between
# Variants of a registered solver with options, by the name the tables give them: the fast
# solver with its C library on two threads (FastSolverOptions.threads), timed in the
# scenario sweep (experiments.benchmark.suites.sweep_scenarios).
SOLVER_VARIANTS: dict[str, tuple[str, dict[str, Any]]] = {"fast_2threads": ("fast", {"threads": 2})}
# The objective reference: the first of these that is available.
REFERENCES = ("ipopt_multiple_shooting", "ipopt", "csnlp")

NO_SLACK_TOL = 1e-6  # total slack below which a reference solution "needs no slack"
GAP_TOL = 1e-4  # relative objective gap of the accuracy checks
LOCAL_OPTIMUM_RTOL = 1e-9  # a probed descent above -this * |J| certifies a local optimum

Problem = tuple[int, int, np.ndarray, np.ndarray]  # (seed, step, x0, W)


def build_solver(
    name: str, problem: ScenarioProblem, **options: Any
) -> tuple[Any | None, float, str]:
    """Build solver ``name`` through the registry.

    Returns:
        ``(solver, build_time [s], reason)``: ``solver`` ``None`` when it cannot be built.

    Raises:
        ValueError: for a name not in :data:`controllers.solvers.SOLVERS`.
    """
    solver_spec(name)  # (an unknown name raises)
    raise_if_interrupted()
    t0 = time.perf_counter()
    try:
        solver = make_solver(problem, name, **options)
    except Exception as exc:  # unavailable, reported in the table, never a crashed run
        raise_if_interrupted()  # a Ctrl-C turned into another error stops the run
        return None, math.nan, f"{type(exc).__name__}: {exc}"
    return solver, time.perf_counter() - t0, ""


def build_solvers(
    problem: ScenarioProblem, solvers: Iterable[tuple[str, str, Mapping[str, Any]]]
) -> tuple[dict[str, Any], dict[str, dict[str, Any]]]:
    """Build every ``(label, registry name, options)`` of ``solvers`` (:func:`build_solver`):
    ``(built by label, {label: {"available", "reason", "build_time_s"}})``.
    """
    built, info = {}, {}
    for label, name, options in solvers:
        solver, build_time, reason = build_solver(name, problem, **options)
        info[label] = {
            "available": solver is not None,
            "reason": reason,
            "build_time_s": build_time,
        }
        if solver is not None:
            built[label] = solver
    return built, info


def solve_record(
    solver: Any,
    problem: ScenarioProblem,
    x0: np.ndarray,
    W: np.ndarray,
    u_guess: np.ndarray | None = None,
) -> dict[str, Any]:
    """Solve once and measure; every accuracy figure is recomputed from the returned ``u``.

    Returns:
        ``solve_time_ms`` (the solver's own), ``wall_time_ms``, ``iterations``, ``success``,
        ``status``, ``objective``, ``slack``, ``max_violation`` (constraint units) and ``u``;
        a solve that raises is a failed record with NaN figures.
    """
    raise_if_interrupted()
    t0 = time.perf_counter()
    try:
        sol = solver.solve(x0, W, u_guess=u_guess)
    except Exception as exc:  # a crashing solver is a failed solve, not a crashed benchmark
        raise_if_interrupted()
        return {
            "solve_time_ms": math.nan,
            "wall_time_ms": 1e3 * (time.perf_counter() - t0),
            "iterations": 0,
            "success": False,
            "status": f"raised {type(exc).__name__}: {exc}",
            "objective": math.nan,
            "slack": math.nan,
            "max_violation": math.nan,
            "u": None,
        }
    wall = time.perf_counter() - t0
    raise_if_interrupted()  # stopped by a Ctrl-C: not a failed solve to record
    X = problem.rollout(x0, W, sol.u)
    return {
        "solve_time_ms": 1e3 * float(sol.solve_time),
        "wall_time_ms": 1e3 * wall,
        "iterations": int(sol.iterations),
        "success": bool(sol.success),
        "status": str(sol.status),
        "objective": problem.objective(x0, W, sol.u),
        "slack": float(np.sum(problem.minimal_slack(X))),
        "max_violation": problem.constraint_violation(X),
        "u": np.asarray(sol.u, dtype=float).tolist(),
    }


def run_interleaved(
    solvers: dict[str, Any],
    problem: ScenarioProblem,
    sequence: Sequence[Problem],
    warmup: bool = True,
    progress: bool = False,
    desc: str = "solves",
) -> dict[str, list[dict[str, Any]]]:
    """Every solver solves every problem of ``sequence`` in order, interleaved per problem in a
    rotating order, reset at each new seed, else warm-started from its own past.

    Returns:
        name -> one :func:`solve_record` per problem, with ``seed``, ``step``, ``warm_start``.
    """
    names = list(solvers)
    records: dict[str, list[dict[str, Any]]] = {name: [] for name in names}
    if not names or not sequence:
        return records
    if warmup:
        # One untimed solve absorbs first-call costs (allocations, lazy set-up).
        _, _, x0, W = sequence[0]
        for name in names:
            solvers[name].reset()
            solve_record(solvers[name], problem, x0, W)
    prev_seed = None
    for j, (seed, step, x0, W) in enumerate(tqdm(sequence, desc=desc, disable=not progress)):
        warm = seed == prev_seed  # the first problem of a closed loop starts from zeros
        if not warm:
            for solver in solvers.values():
                solver.reset()
            prev_seed = seed
        shift = j % len(names)
        for name in names[shift:] + names[:shift]:
            rec = solve_record(solvers[name], problem, x0, W)
            records[name].append({"seed": int(seed), "step": int(step), "warm_start": warm, **rec})
    return records


def _finite(values: Iterable[float]) -> np.ndarray:
    a = np.asarray(list(values), dtype=float)
    return a[np.isfinite(a)]


def stat(values: Iterable[float], fn: Callable[[np.ndarray], Any]) -> float:
    """``fn`` of the finite ``values`` (NaN when there are none)."""
    a = _finite(values)
    return float(fn(a)) if a.size else math.nan


def p95(a: np.ndarray) -> float:
    """95th percentile."""
    return float(np.percentile(a, 95))


def timing_summary(records: list[dict[str, Any]]) -> dict[str, Any]:
    """Medians, percentiles and counts of one solver's records (times in ms): times of the
    warm-started solves, the first of each loop apart (``n_cold``, ``cold_solve_ms_max``).
    """
    warm = [r for r in records if r.get("warm_start", True)]
    cold = [r["solve_time_ms"] for r in records if not r.get("warm_start", True)]
    solve = [r["solve_time_ms"] for r in warm]
    wall = [r["wall_time_ms"] for r in warm]
    iters = [r["iterations"] for r in warm]
    return {
        "n_problems": len(records),
        "n_cold": len(cold),
        "cold_solve_ms_max": stat(cold, np.max),
        "n_success": int(sum(r["success"] for r in records)),
        # Solves that raised have no solve time: count them so they cannot hide.
        "n_raised": int(sum(r["status"].startswith("raised") for r in records)),
        "solve_ms_median": stat(solve, np.median),
        "solve_ms_p95": stat(solve, p95),
        "solve_ms_max": stat(solve, np.max),
        "wall_ms_median": stat(wall, np.median),
        "wall_ms_p95": stat(wall, p95),
        "wall_ms_max": stat(wall, np.max),
        "iterations_median": stat(iters, np.median),
        "iterations_max": stat(iters, np.max),
        "slack_max": stat([r["slack"] for r in records], np.max),
        "max_violation": stat([r["max_violation"] for r in records], np.max),
    }


def relative_gap(rec: dict[str, Any], ref: dict[str, Any]) -> float:
    """``(J - J_ref) / |J_ref|`` of two records (negative: ``rec`` is lower)."""
    return (rec["objective"] - ref["objective"]) / max(abs(ref["objective"]), 1e-12)


def worse_problems(
    records: list[dict[str, Any]], reference: list[dict[str, Any]], tol: float = GAP_TOL
) -> list[dict[str, Any]]:
    """The problems where a solver ends more than ``tol`` (relative) above the reference, among
    those the reference solved: ``[{"seed", "step", "rel_gap" (NaN if raised), "success"}]``.
    """
    out = []
    for rec, ref in zip(records, reference, strict=True):
        if not ref["success"]:
            continue
        gap = relative_gap(rec, ref)
        if not gap <= tol:  # NaN (a raised solve) is listed too
            out.append(
                {
                    "seed": rec["seed"],
                    "step": rec["step"],
                    "rel_gap": gap,
                    "success": rec["success"],
                }
            )
    return out


def accuracy_summary(
    records: list[dict[str, Any]], reference: list[dict[str, Any]]
) -> dict[str, Any]:
    """Objective gaps to the reference (where both solved) and violations where the reference
    needs no slack; ``worse_than_reference`` and ``n_reference_ok`` over every reference solve.
    """
    gaps, abs_gaps, violations = [], [], []
    for rec, ref in zip(records, reference, strict=True):
        if rec["success"] and ref["success"]:
            gaps.append(relative_gap(rec, ref))
            abs_gaps.append(rec["objective"] - ref["objective"])
        if ref["success"] and ref["slack"] <= NO_SLACK_TOL:
            violations.append(rec["max_violation"])
    rel = np.asarray(gaps, dtype=float)
    return {
        "n_compared": len(gaps),
        "rel_gap_abs_median": stat(np.abs(rel), np.median),
        "rel_gap_abs_max": stat(np.abs(rel), np.max),
        "rel_gap_min": stat(rel, np.min),
        "rel_gap_max": stat(rel, np.max),
        "abs_gap_max": stat(np.abs(np.asarray(abs_gaps, dtype=float)), np.max),
        "n_worse": int(np.sum(rel > GAP_TOL)),
        "n_better": int(np.sum(rel < -GAP_TOL)),
        "n_reference_ok": int(sum(ref["success"] for ref in reference)),
        "worse_than_reference": worse_problems(records, reference),
        "n_no_slack": len(violations),
        # A NaN violation (a crashed solve) must not hide: count it as infinite.
        "max_violation_no_slack": (
            float(np.max(np.nan_to_num(violations, nan=np.inf))) if violations else math.nan
        ),
    }


def restart_check(
    solvers: dict[str, Any],
    problem: ScenarioProblem,
    problems: Sequence[Problem],
    records: dict[str, list[dict[str, Any]]],
    reference: str,
    summary: dict[str, dict[str, Any]],
) -> None:
    """Re-solve the problems whose objective gap exceeds :data:`GAP_TOL` from the reference's
    solution (untimed): a vanishing gap means another local optimum, not an inaccurate one.
    Adds ``restart_from_reference`` to the records and ``n_restarted``,
    ``restart_rel_gap_abs_max``, ``restart_rel_gap_max`` to ``summary``.
    """
    for name, solver in solvers.items():
        if name == reference:
            continue
        gaps = []
        for j, (_, _, x0, W) in enumerate(problems):
            rec, ref = records[name][j], records[reference][j]
            if not (rec["success"] and ref["success"]) or abs(relative_gap(rec, ref)) <= GAP_TOL:
                continue
            solver.reset()
            again = solve_record(solver, problem, x0, W, u_guess=np.asarray(ref["u"]))
            gap = relative_gap(again, ref) if again["success"] else math.nan
            rec["restart_from_reference"] = {
                "objective": again["objective"],
                "success": again["success"],
                "rel_gap": gap,
            }
            gaps.append(gap)
        summary[name]["n_restarted"] = len(gaps)
        summary[name]["restart_rel_gap_abs_max"] = (
            float(np.max(np.abs(np.nan_to_num(gaps, nan=np.inf)))) if gaps else math.nan
        )
        # Signed: a solver with extra starts may also leave the reference's point for a
        # lower one (negative gap); only a positive gap would be an inaccuracy.
        summary[name]["restart_rel_gap_max"] = (
            float(np.max(np.nan_to_num(gaps, nan=np.inf))) if gaps else math.nan
        )


def certify_lower_plans(
    problem: ScenarioProblem,
    problems: Sequence[Problem],
    records: dict[str, list[dict[str, Any]]],
    reference: str,
    summary: dict[str, dict[str, Any]],
) -> None:
    """Probe plans below the reference by more than :data:`GAP_TOL` for local optimality
    (:func:`controllers.problem.largest_local_descent`); adds ``local_descent`` to the records
    and ``n_better_certified`` to ``summary``.
    """
    from controllers.problem import largest_local_descent

    for name in records:
        if name == reference:
            continue
        certified = 0
        for j, (_, _, x0, W) in enumerate(problems):
            rec, ref = records[name][j], records[reference][j]
            if not (rec["success"] and ref["success"]) or rec["u"] is None:
                continue
            if relative_gap(rec, ref) >= -GAP_TOL:
                continue
            descent = largest_local_descent(problem, x0, W, np.asarray(rec["u"]))
            rec["local_descent"] = descent
            certified += descent >= -LOCAL_OPTIMUM_RTOL * abs(rec["objective"])
        summary[name]["n_better_certified"] = certified


def speedups(
    summary: dict[str, dict[str, Any]], records: dict[str, list[dict]], base: str = "fast"
) -> dict[str, dict[str, float]]:
    """Every solver's times over ``base``'s (> 1: ``base`` is faster), median and per problem."""
    if base not in summary:
        return {}
    out = {}
    b = summary[base]
    for name, s in summary.items():
        if name == base:
            continue
        per_problem = [
            r["solve_time_ms"] / f["solve_time_ms"]
            for r, f in zip(records[name], records[base], strict=True)
            if f["solve_time_ms"] > 0
        ]
        out[name] = {
            "median_ratio": s["solve_ms_median"] / b["solve_ms_median"],
            "wall_median_ratio": s["wall_ms_median"] / b["wall_ms_median"],
            "per_problem_median_ratio": stat(per_problem, np.median),
        }
    return out


def _alone(
    built: dict[str, Any],
    problem: ScenarioProblem,
    problems: Sequence[Problem],
    records: dict[str, list[dict[str, Any]]],
    warmup: bool,
    progress: bool,
) -> tuple[dict[str, dict[str, Any]], list[dict[str, Any]]]:
    """The fast solver's closed loop again without other solves in between (their cache
    evictions); ``plan_difference_max`` against the side-by-side plans.

    Returns:
        ``(timing figures per fast solver, their failed solves)``.
    """
    fast = {name: built[name] for name in FAST_SOLVERS if name in built}
    if not fast or len(fast) == len(built):
        return {}, []
    solo = run_interleaved(fast, problem, problems, warmup, progress, "fast solvers alone")
    failed = failures_of(solo, "closed_loop_alone", problem.horizon, problem.n_scenarios)
    out = {}
    for name, recs in solo.items():
        out[name] = timing_summary(recs)
        out[name]["plan_difference_max"] = max(
            (
                float(np.max(np.abs(np.subtract(a["u"], b["u"]))))
                for a, b in zip(recs, records[name], strict=True)
                if a["u"] is not None and b["u"] is not None
            ),
            default=math.nan,
        )
    return out, failed


def time_solvers(
    problems: Sequence[Problem],
    solvers: Sequence[str] = SOLVERS,
    problem: ScenarioProblem | None = None,
    config: Any = DEFAULT_CONFIG,
    warmup: bool = True,
    progress: bool = False,
) -> dict[str, Any]:
    """Time solvers side by side on closed-loop problems, each warm-started from its own past,
    then re-solve gaps from the reference, probe lower plans and run the fast solver alone.

    Args:
        problems: ``(seed, step, x0, W)`` tuples (:func:`.problems.record_problems`).
        solvers: names from :data:`controllers.solvers.SOLVERS`.
        problem: the problem data; by default from ``config`` at the first ``W``'s size.
        config: used only when ``problem`` is ``None``.
        warmup: one untimed solve per solver before timing.
        progress: show progress bars.

    Returns:
        ``{"problem", "n_problems", "problems", "solvers", "reference", "records",
        "summary", "speedup", "alone", "failures"}``; times in ms, build times in s.

    Raises:
        ValueError: for an unknown solver name, or no problems and no ``problem``.
    """
    problems = list(problems)
    for name in solvers:
        solver_spec(name)  # (an unknown name raises)
    if problem is None:
        if not problems:
            raise ValueError("problems is empty: cannot infer the problem size")
        ns, n = np.shape(problems[0][3])[:2]
        problem = problem_from_config(config, n_scenarios=int(ns), horizon=int(n))
    built, info = build_solvers(problem, [(name, name, {}) for name in solvers])
    for name in solvers:
        info[name]["label"] = SOLVER_LABELS[name]
    records = run_interleaved(built, problem, problems, warmup, progress, "closed-loop solves")
    reference = next((r for r in REFERENCES if r in built), None)
    summary = {}
    for name, recs in records.items():
        summary[name] = timing_summary(recs)
        summary[name]["build_time_s"] = info[name]["build_time_s"]
        if reference is not None:
            summary[name].update(accuracy_summary(recs, records[reference]))
    if reference is not None:
        restart_check(built, problem, problems, records, reference, summary)
        certify_lower_plans(problem, problems, records, reference, summary)
    alone, alone_failures = _alone(built, problem, problems, records, warmup, progress)
    failed = failures_of(records, "closed_loop", problem.horizon, problem.n_scenarios)
    return {
        "problem": {"horizon": problem.horizon, "n_scenarios": problem.n_scenarios},
        "n_problems": len(problems),
        "problems": [{"seed": int(p[0]), "step": int(p[1])} for p in problems],
        "solvers": info,
        "reference": reference,
        "records": records,
        "summary": summary,
        "speedup": speedups(summary, records),
        "alone": alone,
        "failures": failed + alone_failures,
    }
