"""Speed and accuracy benchmark of the scenario MPC solvers, the particle filter and an episode.

The benchmark answers the solver issues' questions with measurements, never with asserts
(``lfm-benchmark``, :func:`main`):

* **Closed-loop problems** (:mod:`experiments.bench_problems`): paper episodes with the
  scenario agent, recording the ``(x0, W)`` it met at every step.
* **Solvers side by side** (:mod:`experiments.bench_solvers`): every solver of the registry
  (:data:`controllers.solvers.SOLVERS`: ``fast``, ``fast_bicycle``, ``ipopt``,
  ``ipopt_multiple_shooting`` (the textbook reference), ``csnlp``) solves these problems in
  closed-loop order, warm-started from its own past, interleaved problem by problem; times,
  iterations, objectives (:meth:`~controllers.problem.ScenarioProblem.objective` of the
  returned inputs) and violations; then the fast solvers again alone.
* **Scenario-count sweep, particle filter, whole episode** (:mod:`experiments.bench_suites`).
* **Verdicts and report** (:mod:`experiments.bench_report`): the speed table, PASS/FAIL per
  target with the measured figure, JSON (``--out``) and the speed table as Markdown (beside
  it, ``.md``).

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
from experiments.bench_problems import (
    DEFAULT_CONFIG,
    DEFAULT_SEEDS,
    RECORDING_SOLVER,
    experiment_config,
    problem_from_config,
    record_closed_loop,
    record_problems,
)
from experiments.bench_report import (
    evaluate_targets,
    format_markdown,
    format_report,
    json_ready,
    speed_targets,
)
from experiments.bench_solvers import build_solver, time_solvers
from experiments.bench_suites import (
    DEFAULT_PF_SIZES,
    DEFAULT_SWEEP_NS,
    DEFAULT_SWEEP_STEPS,
    sweep_scenarios,
    time_episode,
    time_particle_filter,
)
from experiments.cli import one_line_errors

DEFAULT_OUT = "results/benchmark.json"
# Recorded steps per seed: a paper episode with the fast solver takes ~45 steps, so 50 keeps
# whole episodes while capping a failing one (151 steps).
DEFAULT_MAX_STEPS = 50
# --quick: a smoke run of every part (a few problems, a small sweep and filter).
QUICK = {
    "seeds": "0",
    "max_steps": 3,
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


def run_benchmark(
    config: Any = DEFAULT_CONFIG,
    seeds: Sequence[int] = DEFAULT_SEEDS,
    max_steps: int = DEFAULT_MAX_STEPS,
    solvers: Sequence[str] = SOLVERS,
    sweep_ns: Sequence[int] = DEFAULT_SWEEP_NS,
    sweep_steps_per_seed: int | None = DEFAULT_SWEEP_STEPS,
    pf_sizes: Sequence[int] = DEFAULT_PF_SIZES,
    pf_steps: int = 200,
    progress: bool = True,
) -> dict[str, Any]:
    """Run every part of the benchmark and judge the targets.

    Args:
        config: a YAML path, a dict (whole file), an ExperimentConfig or ``None``.
        seeds: episode seeds for the recorded problems.
        max_steps: recorded steps per seed.
        solvers: solvers of the closed-loop comparison (names from
            :data:`controllers.solvers.SOLVERS`).
        sweep_ns: scenario counts of the sweep (empty: no sweep).
        sweep_steps_per_seed: anchors per seed in the sweep.
        pf_sizes: particle-filter sizes (empty: no filter timing).
        pf_steps: timed filter steps per size.
        progress: show progress bars.

    Returns:
        All figures: ``meta``, ``closed_loop``, ``sweep``, ``particle_filter``, ``episode``
        and ``targets``.

    Raises:
        ValueError: for an unknown solver name or a bad config.
    """
    for name in solvers:
        if name not in SOLVERS:
            raise ValueError(f"unknown solver {name!r}; choose one of {SOLVERS}")
    t0 = time.perf_counter()
    cfg = experiment_config(config)
    meta: dict[str, Any] = {
        "config": str(config),
        "seeds": list(seeds),
        "max_steps": int(max_steps),
        "solvers": list(solvers),
        "recording_solver": RECORDING_SOLVER,
        "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "platform": platform.platform(),
        "cpu_count": os.cpu_count(),
        "load_average_start": _load(),
        "versions": _versions(),
        "times_unit": "ms unless the key ends in _s",
    }
    problems, anchors = record_closed_loop(cfg, seeds, max_steps, progress)
    results: dict[str, Any] = {"meta": meta}
    results["closed_loop"] = time_solvers(problems, solvers, config=cfg, progress=progress)
    if sweep_ns:
        results["sweep"] = sweep_scenarios(
            sweep_ns,
            horizon=results["closed_loop"]["problem"]["horizon"],
            config=cfg,
            anchors=anchors,
            steps_per_seed=sweep_steps_per_seed,
            progress=progress,
        )
    if pf_sizes:
        results["particle_filter"] = time_particle_filter(pf_sizes, config=cfg, n_steps=pf_steps)
    results["episode"] = time_episode(cfg, seed=int(seeds[0]))
    results["targets"] = evaluate_targets(results)
    meta["load_average_end"] = _load()
    meta["total_time_s"] = time.perf_counter() - t0
    return results


# --------------------------------------------------------------------------- command line


def parse_seeds(text: str) -> list[int]:
    """Seeds from ``"0:3"`` (end exclusive), ``"5"`` or ``"1,4,7"`` (ranges may be mixed in).

    The syntax of :func:`experiments.evaluation.parse_seeds`, with the error worded for
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
            "closed-loop problems, a scenario-count sweep, the particle filter and one "
            "episode; print the speed table and PASS/FAIL per target, write JSON and the "
            "speed table as Markdown."
        ),
    )
    parser.add_argument(
        "--config", default=DEFAULT_CONFIG, help="config YAML (default: %(default)s)"
    )
    parser.add_argument(
        "--seeds",
        default=None,
        help="episode seeds, e.g. '0:3' or '0,5' (default: 0:3; quick: 0)",
    )
    parser.add_argument(
        "--max-steps",
        type=_positive_int,
        default=None,
        help=f"recorded steps per seed (default: {DEFAULT_MAX_STEPS}; quick: {QUICK['max_steps']})",
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
        "--quick",
        action="store_true",
        help="a smoke run: few problems, a small sweep and filter (the figures mean little)",
    )
    parser.add_argument(
        "--out",
        default=DEFAULT_OUT,
        help="JSON output (default: %(default)s); the Markdown table goes beside it (.md)",
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")
    return parser


@one_line_errors("lfm-benchmark")
def main(argv: Sequence[str] | None = None) -> int:
    """Command line: run the benchmark, print the report, write JSON and Markdown."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        seeds = parse_seeds(args.seeds or (QUICK["seeds"] if args.quick else "0:3"))
    except ValueError as exc:
        parser.error(str(exc))
    options: dict[str, Any] = {}
    if args.quick:
        options = {k: v for k, v in QUICK.items() if k != "seeds"}
    if args.max_steps is not None:
        options["max_steps"] = args.max_steps
    options.setdefault("max_steps", DEFAULT_MAX_STEPS)
    results = run_benchmark(
        config=args.config,
        seeds=seeds,
        solvers=[s for s in SOLVERS if s not in args.skip],
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
    print(f"\nwrote {out} and {markdown}")
    return 0


__all__ = [
    "DEFAULT_CONFIG",
    "build_parser",
    "build_solver",
    "main",
    "parse_seeds",
    "problem_from_config",
    "record_problems",
    "run_benchmark",
    "speed_targets",
]

if __name__ == "__main__":
    raise SystemExit(main())
