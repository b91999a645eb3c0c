"""Speed and accuracy benchmark of the scenario MPC solvers, the particle filter and an episode.

The benchmark answers the solver issues' questions with measurements, never with asserts
(``lfm-benchmark``, :func:`main`):

* **Closed-loop problems** (:mod:`experiments.benchmark.problems`): paper episodes with the
  scenario agent (seeds 0..5), recording the ``(x0, W)`` it met at every step.
* **Solvers side by side** (:mod:`experiments.benchmark.solvers`): the solvers of the registry
  (:data:`controllers.solvers.SOLVERS`; by default all but ``csnlp``: ``fast``,
  ``fast_bicycle``, ``ipopt``, ``ipopt_multiple_shooting`` (the textbook reference),
  ``sqpmethod`` (CasADi's SQP + qpOASES, JIT-compiled: the anchor)) solve these problems in
  closed-loop order, warm-started from their own past, interleaved problem by problem;
  times, iterations, objectives (:meth:`~controllers.problem.ScenarioProblem.objective` of
  the returned inputs) and violations; then the fast solvers again alone.
* **Horizons, scenario counts, first solve, particle filter, whole episode**
  (:mod:`experiments.benchmark.suites`): fast and IPOPT at ``N`` = 7, 15, 30; ``Ns`` up to
  5000; a fresh fast solver's build and first solve (compilation included); the filter
  with 7000 particles; one episode.
* **Failures**: every failed solve of every solver and part, with its problem's id.
* **Verdicts and report** (:mod:`experiments.benchmark.targets`,
  :mod:`experiments.benchmark.report`): PASS/FAIL per target with the measured figure,
  JSON (``--out``) and the speed table and targets as Markdown (beside it, ``.md``).
  ``--check`` exits 1 when a target fails.

Timing is noisy on a shared machine: the figures are medians and percentiles of one run.
A solver that cannot be built (an optional package missing) is listed as unavailable with
the reason, and its targets are SKIP.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from collections.abc import Sequence
from importlib import metadata
from pathlib import Path
from typing import Any

from controllers.solvers import SOLVERS
from experiments.benchmark.problems import (
    DEFAULT_CONFIG,
    DEFAULT_SEEDS,
    RECORDING_SOLVER,
    experiment_config,
    problem_from_config,
    record_closed_loop,
    record_problems,
)
from experiments.benchmark.report import format_markdown, format_report, json_ready
from experiments.benchmark.solvers import build_solver, time_solvers
from experiments.benchmark.suites import (
    DEFAULT_HORIZON_STEPS,
    DEFAULT_HORIZONS,
    DEFAULT_PF_SIZES,
    DEFAULT_SWEEP_NS,
    DEFAULT_SWEEP_STEPS,
    first_solve,
    sweep_horizons,
    sweep_scenarios,
    time_episode,
    time_particle_filter,
)
from experiments.benchmark.targets import (
    DEFAULT_THRESHOLDS,
    check_thresholds,
    evaluate_targets,
    failed_targets,
    speed_targets,
)
from experiments.cli import one_line_errors

DEFAULT_OUT = "results/benchmark.json"
# Recorded steps per seed: a paper episode with the fast solver takes ~45 steps, so 50 keeps
# whole episodes while capping a failing one (151 steps).
DEFAULT_MAX_STEPS = 50
# csnlp (~0.8 s per problem) is left out of the default run to keep it near 10 minutes.
DEFAULT_SOLVERS = tuple(s for s in SOLVERS if s != "csnlp")
# --quick: a smoke run of every part (a few problems, tiny sweeps and filter).
QUICK = {
    "seeds": "0",
    "max_steps": 3,
    "horizon_steps": 2,
    # [s] per solve at N = 15, 30: a smoke run, not a verdict (failed solves are listed)
    "horizon_max_time": 2.0,
    "sweep_ns": (10, 50),
    "sweep_steps_per_seed": 3,
    "pf_sizes": (1000, 7000),
    "pf_steps": 30,
}


def _versions() -> dict[str, str | None]:
    out: dict[str, str | None] = {"python": platform.python_version()}
    for dist in ("numpy", "casadi", "csnlp", "scipy"):
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            out[dist] = None
    return out


def _load() -> list[float] | None:
    try:
        return [float(x) for x in os.getloadavg()]
    except (AttributeError, OSError):
        return None


def all_failures(results: dict[str, Any]) -> list[dict[str, Any]]:
    """Every failed solve of a result: closed loop, horizons (not reused rows), Ns sweep."""
    out = list(results.get("closed_loop", {}).get("failures", []))
    for row in results.get("horizons", {}).get("results", []):
        if row.get("source") != "closed_loop":
            out += row["failures"]
    for row in results.get("sweep", {}).get("results", []):
        out += row.get("failures", [])
    return out


def run_benchmark(
    config: Any = DEFAULT_CONFIG,
    seeds: Sequence[int] = DEFAULT_SEEDS,
    max_steps: int = DEFAULT_MAX_STEPS,
    solvers: Sequence[str] = DEFAULT_SOLVERS,
    horizons: Sequence[int] = DEFAULT_HORIZONS,
    horizon_steps: dict[int, int] | int | None = None,
    horizon_max_time: dict[str, float] | float | None = None,
    sweep_ns: Sequence[int] = DEFAULT_SWEEP_NS,
    sweep_steps_per_seed: int | None = DEFAULT_SWEEP_STEPS,
    pf_sizes: Sequence[int] = DEFAULT_PF_SIZES,
    pf_steps: int = 200,
    thresholds: dict[str, float] | None = None,
    progress: bool = True,
) -> dict[str, Any]:
    """Run every part of the benchmark and judge the targets.

    Args:
        config: a YAML path, a dict (whole file), an ExperimentConfig or ``None``.
        seeds: episode seeds for the recorded problems.
        max_steps: recorded steps per seed.
        solvers: solvers of the closed-loop comparison (names from
            :data:`controllers.solvers.SOLVERS`).
        horizons: horizons ``N`` of the horizon sweep (empty: none).
        horizon_steps: problems per seed at each horizon (an int, or a dict by ``N``;
            default :data:`experiments.benchmark.suites.DEFAULT_HORIZON_STEPS`).
        horizon_max_time: wall-clock limit of one solve in the horizon sweep [s], one for
            both solvers or a dict by name (default
            :data:`experiments.benchmark.suites.HORIZON_MAX_TIME_S`).
        sweep_ns: scenario counts of the sweep (empty: no sweep).
        sweep_steps_per_seed: anchors per seed in the sweep.
        pf_sizes: particle-filter sizes (empty: no filter timing).
        pf_steps: timed filter steps per size.
        thresholds: target thresholds to change, by key
            (:data:`experiments.benchmark.targets.DEFAULT_THRESHOLDS`).
        progress: show progress bars.

    Returns:
        All figures: ``meta``, ``closed_loop``, ``horizons``, ``sweep``, ``first_solve``,
        ``particle_filter``, ``episode``, ``failures`` and ``targets``.

    Raises:
        ValueError: for an unknown solver name or threshold key, or a bad config.
    """
    for name in solvers:
        if name not in SOLVERS:
            raise ValueError(f"unknown solver {name!r}; choose one of {SOLVERS}")
    thresholds = check_thresholds(thresholds)
    t0 = time.perf_counter()
    cfg = experiment_config(config)
    meta: dict[str, Any] = {
        "config": str(config),
        "seeds": list(seeds),
        "max_steps": int(max_steps),
        "solvers": list(solvers),
        "recording_solver": RECORDING_SOLVER,
        "thresholds": thresholds,
        "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "platform": platform.platform(),
        "cpu_count": os.cpu_count(),
        "load_average_start": _load(),
        "versions": _versions(),
        "times_unit": "ms unless the key ends in _s",
    }
    part_times: dict[str, float] = {}
    meta["part_times_s"] = part_times

    def timed(name: str, fn: Any, *args: Any, **kwargs: Any) -> Any:
        start = time.perf_counter()
        out = fn(*args, **kwargs)
        part_times[name] = time.perf_counter() - start
        return out

    problems, anchors = timed("record", record_closed_loop, cfg, seeds, max_steps, progress)
    results: dict[str, Any] = {"meta": meta}
    results["closed_loop"] = timed(
        "closed_loop", time_solvers, problems, solvers, config=cfg, progress=progress
    )
    if horizons:
        results["horizons"] = timed(
            "horizons",
            sweep_horizons,
            horizons,
            config=cfg,
            seeds=seeds,
            steps_per_seed=horizon_steps,
            closed_loop=results["closed_loop"],
            max_time=horizon_max_time,
            progress=progress,
            closed_loop_problems=problems,
        )
    if sweep_ns:
        results["sweep"] = timed(
            "sweep",
            sweep_scenarios,
            sweep_ns,
            horizon=results["closed_loop"]["problem"]["horizon"],
            config=cfg,
            anchors=anchors,
            steps_per_seed=sweep_steps_per_seed,
            progress=progress,
        )
    first = (problems[0].x0, problems[0].W) if problems else None
    results["first_solve"] = timed("first_solve", first_solve, cfg, first)
    if pf_sizes:
        results["particle_filter"] = timed(
            "particle_filter", time_particle_filter, pf_sizes, config=cfg, n_steps=pf_steps
        )
    results["episode"] = timed("episode", time_episode, cfg, seed=int(seeds[0]))
    results["failures"] = all_failures(results)
    results["targets"] = evaluate_targets(results, thresholds)
    meta["load_average_end"] = _load()
    meta["total_time_s"] = time.perf_counter() - t0
    return results


# --------------------------------------------------------------------------- command line


def parse_seeds(text: str) -> list[int]:
    """Seeds from ``"0:3"`` (end exclusive), ``"5"`` or ``"1,4,7"`` (ranges may be mixed in).

    The syntax of :func:`experiments.evaluation.run.parse_seeds`, with the error worded for
    this command line.

    Raises:
        ValueError: naming ``text`` when it is not a list of non-negative integers and
            non-empty ranges.
    """
    from experiments.evaluation import parse_seeds as parse

    try:
        return parse(text)
    except ValueError:
        raise ValueError(
            f"seeds={text!r}: expected non-negative integers and ranges like '0:3' or '1,4,7'"
        ) from None


def parse_ints(text: str, name: str) -> list[int]:
    """Positive integers from ``"7,15,30"``.

    Raises:
        ValueError: naming ``name`` when an entry is not an integer >= 1.
    """
    try:
        values = [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        values = []
    if not values or min(values) < 1:
        raise ValueError(f"{name}={text!r}: expected integers >= 1 separated by commas")
    return values


def parse_threshold(text: str) -> tuple[str, float]:
    """``KEY=VALUE`` of ``--threshold``, checked against the known keys.

    Raises:
        argparse.ArgumentTypeError: naming the bad key or value and the known keys.
    """
    key, sep, value = text.partition("=")
    try:
        if not sep:
            raise ValueError(f"threshold {text!r}: expected KEY=VALUE")
        return key, check_thresholds({key.strip(): value})[key.strip()]
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: must be an integer >= 1")
    return value


def build_parser() -> argparse.ArgumentParser:
    """The ``lfm-benchmark`` argument parser."""
    parser = argparse.ArgumentParser(
        prog="lfm-benchmark",
        description=(
            f"Benchmark the scenario MPC solvers ({', '.join(SOLVERS)}) side by side on "
            "closed-loop problems, at several horizons and scenario counts, the particle "
            "filter and one episode; print the speed table, every failed solve and "
            "PASS/FAIL per target, write JSON and the speed table as Markdown."
        ),
    )
    parser.add_argument(
        "--config", default=DEFAULT_CONFIG, help="config YAML (default: %(default)s)"
    )
    parser.add_argument(
        "--seeds",
        default=None,
        help="episode seeds, e.g. '0:6' or '0,5' (default: 0:6; quick: 0)",
    )
    parser.add_argument(
        "--max-steps",
        type=_positive_int,
        default=None,
        help=f"recorded steps per seed (default: {DEFAULT_MAX_STEPS}; quick: {QUICK['max_steps']})",
    )
    parser.add_argument(
        "--solvers",
        default=",".join(DEFAULT_SOLVERS),
        help=f"solvers of the comparison, comma-separated (default: %(default)s; all: "
        f"{','.join(SOLVERS)})",
    )
    parser.add_argument(
        "--skip",
        action="append",
        default=[],
        choices=SOLVERS,
        metavar="SOLVER",
        help=f"leave a solver out of the comparison (repeatable; one of {', '.join(SOLVERS)})",
    )
    parser.add_argument(
        "--horizons",
        default=",".join(str(n) for n in DEFAULT_HORIZONS),
        help="horizons N of the horizon sweep, comma-separated (default: %(default)s)",
    )
    parser.add_argument(
        "--horizon-steps",
        type=_positive_int,
        default=None,
        help="problems per seed at each horizon other than the config's (default: "
        + ", ".join(f"N={n}: {k}" for n, k in DEFAULT_HORIZON_STEPS.items())
        + f"; quick: {QUICK['horizon_steps']})",
    )
    parser.add_argument(
        "--threshold",
        action="append",
        default=[],
        type=parse_threshold,
        metavar="KEY=VALUE",
        help="change a target's threshold (repeatable); keys: " + ", ".join(DEFAULT_THRESHOLDS),
    )
    parser.add_argument(
        "--check",
        action="store_true",
        help="exit with status 1 when any target FAILS (SKIP is no failure)",
    )
    parser.add_argument(
        "--quick",
        action="store_true",
        help="a smoke run: few problems, tiny sweeps and filter (the figures mean little)",
    )
    parser.add_argument(
        "--out",
        default=DEFAULT_OUT,
        help="JSON output (default: %(default)s); the Markdown table goes beside it (.md)",
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")
    return parser


def _solver_list(text: str, skip: Sequence[str]) -> list[str]:
    names = [s.strip() for s in text.split(",") if s.strip()]
    for name in names:
        if name not in SOLVERS:
            raise ValueError(f"solvers: unknown solver {name!r}; choose from {', '.join(SOLVERS)}")
    return [s for s in names if s not in skip]


@one_line_errors("lfm-benchmark")
def main(argv: Sequence[str] | None = None) -> int:
    """Command line: run the benchmark, print the report, write JSON and Markdown.

    Returns:
        0, or 1 with ``--check`` when a target fails.
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        seeds = parse_seeds(args.seeds or (QUICK["seeds"] if args.quick else "0:6"))
        solvers = _solver_list(args.solvers, args.skip)
        horizons = parse_ints(args.horizons, "horizons")
    except ValueError as exc:
        parser.error(str(exc))
    options: dict[str, Any] = {}
    if args.quick:
        options = {k: v for k, v in QUICK.items() if k != "seeds"}
    if args.max_steps is not None:
        options["max_steps"] = args.max_steps
    if args.horizon_steps is not None:
        options["horizon_steps"] = args.horizon_steps
    options.setdefault("max_steps", DEFAULT_MAX_STEPS)
    results = run_benchmark(
        config=args.config,
        seeds=seeds,
        solvers=solvers,
        horizons=horizons,
        thresholds=dict(args.threshold),
        progress=not args.no_progress,
        **options,
    )
    results["meta"]["argv"] = list(sys.argv[1:] if argv is None else argv)
    print(format_report(results), flush=True)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(json_ready(results), indent=1, allow_nan=False) + "\n")
    markdown = out.with_suffix(".md")
    markdown.write_text(format_markdown(results))
    print(f"\nwrote {out} and {markdown}; {results['meta']['total_time_s']:.0f} s in all")
    failed = failed_targets(results["targets"])
    if args.check and failed:
        print(f"--check: {len(failed)} target(s) FAIL: " + "; ".join(t["key"] for t in failed))
        return 1
    return 0


__all__ = [
    "DEFAULT_CONFIG",
    "DEFAULT_SOLVERS",
    "all_failures",
    "build_parser",
    "build_solver",
    "main",
    "parse_ints",
    "parse_seeds",
    "parse_threshold",
    "problem_from_config",
    "record_problems",
    "run_benchmark",
    "speed_targets",
]

if __name__ == "__main__":
    raise SystemExit(main())
