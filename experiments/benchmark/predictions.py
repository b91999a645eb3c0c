"""The prediction sweep: the fast solver on the open-loop and the feedback scenario problem at
each horizon, on the same problems (scenarios drawn as the agent draws them around a closed
loop's estimates), consecutive anchors warm-started, reset at each seed. Figures are the
solver's own; a failed solve did not converge, ``usable`` says whether it gave a plan.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from typing import Any

import numpy as np
from tqdm.auto import tqdm

from controllers.problem import PREDICTIONS
from controllers.solvers import make_solver
from experiments.benchmark.failures import classify_failure
from experiments.benchmark.problems import (
    DEFAULT_CONFIG,
    DEFAULT_SEEDS,
    experiment_config,
    record_closed_loop,
    scenario_draws,
)
from experiments.benchmark.solvers import p95, stat

#: The horizons of the prediction sweep.
PREDICTION_HORIZONS = (7, 15, 30, 50)
#: Problems per seed at each horizon.
PREDICTION_STEPS = 4
#: The first anchored step of each seed (the paper's car is on the track's first bend).
PREDICTION_FIRST_STEP = 10
#: [s] wall-clock limit of one solve (the agents' default ``max_solve_time``).
PREDICTION_MAX_TIME_S = 10.0


def _record(solver: Any, x0: np.ndarray, W: np.ndarray) -> dict[str, Any]:
    t0 = time.perf_counter()
    try:
        sol = solver.solve(x0, W)
    except Exception as exc:  # a crashing solve is a failed solve, not a crashed benchmark
        return {
            "solve_time_ms": math.nan,
            "wall_time_ms": 1e3 * (time.perf_counter() - t0),
            "iterations": 0,
            "success": False,
            "usable": False,
            "status": f"raised {type(exc).__name__}: {exc}",
            "objective": math.nan,
            "slack": math.nan,
        }
    return {
        "solve_time_ms": 1e3 * float(sol.solve_time),
        "wall_time_ms": 1e3 * (time.perf_counter() - t0),
        "iterations": int(sol.iterations),
        "success": bool(sol.success),
        "usable": bool(sol.usable),
        "status": str(sol.status),
        "objective": float(sol.objective),
        "slack": float(sol.slack),
    }


def _summary(records: list[dict[str, Any]]) -> dict[str, Any]:
    """Times [ms] and iterations of every solve (the first of a seed included)."""
    solve = [r["solve_time_ms"] for r in records]
    slack = np.array([r["slack"] for r in records], dtype=float)
    return {
        "n_problems": len(records),
        "solve_ms_median": stat(solve, np.median),
        "solve_ms_p95": stat(solve, p95),
        "solve_ms_max": stat(solve, np.max),
        "iterations_median": stat([r["iterations"] for r in records], np.median),
        "failed": int(sum(not r["success"] for r in records)),
        "not_usable": int(sum(not r["usable"] for r in records)),
        "infeasible": int(np.sum(slack > 1e-6)),
        "slack_median": stat(slack, np.median),
    }


def sweep_predictions(
    horizons: Sequence[int] = PREDICTION_HORIZONS,
    config: Any = DEFAULT_CONFIG,
    seeds: Sequence[int] = DEFAULT_SEEDS,
    steps_per_seed: int = PREDICTION_STEPS,
    max_time: float = PREDICTION_MAX_TIME_S,
    progress: bool = False,
    first_step: int = PREDICTION_FIRST_STEP,
) -> dict[str, Any]:
    """The fast solver on both predictions at each horizon.

    Args:
        horizons: prediction steps ``N``.
        config: a YAML path, a dict (whole file), an ExperimentConfig or ``None``.
        seeds: env seeds of the recorded episodes.
        steps_per_seed: problems per seed at each ``N`` (consecutive steps).
        max_time: wall-clock limit of one solve [s].
        progress: show progress bars.
        first_step: the first anchored step of each seed.

    Returns:
        ``{"config", "seeds", "steps_per_seed", "first_step", "results": [{"horizon",
        "prediction", "n_scenarios", "summary", "records", "failures"}]}``, times in ms.
    """
    cfg = experiment_config(config)
    last = first_step + steps_per_seed
    _, anchors = record_closed_loop(cfg, seeds, last, progress)
    anchors = [a for a in anchors if a.step >= first_step]
    rows = []
    for n in (int(h) for h in horizons):
        problems = scenario_draws(cfg.make_problem(horizon=n), anchors, np.random.default_rng(0))
        for prediction in PREDICTIONS:
            problem = cfg.make_problem(horizon=n, prediction=prediction)
            solver = make_solver(problem, "fast", max_time=max_time)
            records, prev_seed = [], None
            for p in tqdm(problems, desc=f"N={n} {prediction}", disable=not progress):
                if p.seed != prev_seed:  # a new closed loop: no warm start, no reference
                    solver.reset()
                    prev_seed = p.seed
                records.append({"seed": p.seed, "step": p.step, **_record(solver, p.x0, p.W)})
            failures = [
                {
                    "seed": r["seed"],
                    "step": r["step"],
                    "kind": classify_failure(r["status"]),
                    "status": r["status"],
                    "usable": r["usable"],
                }
                for r in records
                if not r["success"]
            ]
            rows.append(
                {
                    "horizon": n,
                    "prediction": prediction,
                    "n_scenarios": int(problem.n_scenarios),
                    "summary": _summary(records),
                    "records": records,
                    "failures": failures,
                }
            )
    return {
        "config": str(config),
        "seeds": [int(s) for s in seeds],
        "steps_per_seed": int(steps_per_seed),
        "first_step": int(first_step),
        "results": rows,
    }


def format_predictions(result: dict[str, Any]) -> str:
    """The sweep's table (one line per horizon and prediction) and its failed solves."""
    head = (
        f"{'N':>3} {'prediction':<10} {'Ns':>4} {'problems':>8} {'median ms':>10} "
        f"{'p95 ms':>9} {'max ms':>9} {'iter.':>6} {'failed':>6} {'unusable':>8} "
        f"{'slack>1e-6':>10}"
    )
    lines = [
        f"prediction sweep: fast solver, config {result['config']}, seeds "
        f"{result['seeds']}, steps {result['first_step']}.."
        f"{result['first_step'] + result['steps_per_seed'] - 1} of each",
        head,
        "-" * len(head),
    ]
    for row in result["results"]:
        s = row["summary"]
        lines.append(
            f"{row['horizon']:>3} {row['prediction']:<10} {row['n_scenarios']:>4} "
            f"{s['n_problems']:>8} {s['solve_ms_median']:>10.1f} {s['solve_ms_p95']:>9.1f} "
            f"{s['solve_ms_max']:>9.1f} {s['iterations_median']:>6.1f} {s['failed']:>6} "
            f"{s['not_usable']:>8} {s['infeasible']:>10}"
        )
    failed = [(row, f) for row in result["results"] for f in row["failures"]]
    lines.append(f"failed solves (not converged): {len(failed)}")
    for row, f in failed:
        lines.append(
            f"  N={row['horizon']} {row['prediction']} seed {f['seed']} step {f['step']}: "
            f"{f['status']} ({f['kind']}; {'usable plan' if f['usable'] else 'no usable plan'})"
        )
    return "\n".join(lines)
