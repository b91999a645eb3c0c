"""``lfm-benchmark``: the solvers, the particle filter and an episode timed side by side
(:mod:`experiments.benchmark.run`); prints the report, writes JSON and Markdown."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from controllers.solvers import SOLVERS
from controllers.threads import limit_blas_threads
from experiments.benchmark.checks import DEFAULT_THRESHOLDS, check_thresholds, failed_checks
from experiments.benchmark.closed_loop import (
    CLOSED_LOOP_AGENT,
    CLOSED_LOOP_STEPS,
    closed_loop_steps,
    format_closed_loop,
)
from experiments.benchmark.predictions import (
    PREDICTION_STEPS,
    format_predictions,
    sweep_predictions,
)
from experiments.benchmark.report import format_markdown, format_report, json_ready
from experiments.benchmark.run import DEFAULT_MAX_STEPS, DEFAULT_SOLVERS, run_benchmark
from experiments.benchmark.suites import DEFAULT_HORIZON_STEPS, DEFAULT_HORIZONS
from experiments.cli.common import (
    CACHE_NOTE,
    DEFAULT_PRESET,
    add_config_argument,
    check_writable,
    config_argument_path,
    one_line_errors,
)
from experiments.evaluation import parse_seeds as parse_evaluation_seeds

DEFAULT_OUT = "results/benchmark.json"
# --quick: a smoke run of every part (a few problems, tiny sweeps and filter), about a
# minute: the textbook IPOPT form and sqpmethod (its JIT build alone takes 15-50 s) are left
# out unless named with --solvers, and IPOPT at the longer horizons (seconds per problem).
QUICK_SOLVERS = ("fast", "fast_c", "ipopt")
QUICK = {
    "seeds": "0",
    "max_steps": 3,
    "horizon_steps": 2,
    "horizon_solvers": ("fast",),
    # [s] per solve at N = 15, 30: a smoke run, not a verdict (failed solves are listed)
    "horizon_max_time": 2.0,
    "sweep_ns": (10, 50),
    "sweep_steps_per_seed": 3,
    "pf_sizes": (1000, 7000),
    "pf_steps": 30,
}


def parse_seeds(text: str) -> list[int]:
    """Seeds from ``"0:3"`` (end exclusive), ``"5"`` or ``"1,4,7"`` (ranges may be mixed in).

    Raises:
        ValueError: naming ``text`` when it is not non-negative integers and ranges.
    """
    try:
        return parse_evaluation_seeds(text)
    except ValueError:
        raise ValueError(
            f"seeds={text!r}: expected non-negative integers and ranges like '0:3' or '1,4,7'"
        ) from None


def parse_ints(text: str, name: str) -> list[int]:
    """Positive integers from ``"7,15,30"``; ``ValueError`` naming ``name`` otherwise."""
    try:
        values = [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        values = []
    if not values or min(values) < 1:
        raise ValueError(f"{name}={text!r}: expected integers >= 1 separated by commas")
    return values


def parse_threshold(text: str) -> tuple[str, float]:
    """``KEY=VALUE`` of ``--threshold``; ``ArgumentTypeError`` naming a bad key or value."""
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
            "PASS/FAIL/SKIP per check (named bounds on the figures, docs/benchmark.md), "
            "write JSON and the speed table as Markdown."
        ),
        epilog=CACHE_NOTE,
    )
    add_config_argument(parser)
    parser.add_argument(
        "--seeds", default=None, help="episode seeds, e.g. '0:6' or '0,5' (default: 0:6; quick: 0)"
    )
    parser.add_argument(
        "--max-steps",
        type=_positive_int,
        default=None,
        help=f"recorded steps per seed (default: {DEFAULT_MAX_STEPS}; quick: {QUICK['max_steps']})",
    )
    parser.add_argument(
        "--solvers",
        default=None,
        help=f"solvers of the comparison, comma-separated (default: {','.join(DEFAULT_SOLVERS)}; "
        f"quick: {','.join(QUICK_SOLVERS)}; all: {','.join(SOLVERS)})",
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
        help="change a check's bound (repeatable), e.g. fast_c_median_ms=3; keys and "
        "defaults: " + ", ".join(f"{k}={v:g}" for k, v in DEFAULT_THRESHOLDS.items()),
    )
    parser.add_argument(
        "--check",
        action="store_true",
        help="exit with status 1 when any check FAILS (SKIP, a figure not measured, is no failure)",
    )
    parser.add_argument(
        "--quick",
        action="store_true",
        help="a smoke run of every part in about a minute: few problems, tiny sweeps and "
        f"filter, the solvers {','.join(QUICK_SOLVERS)}, the longer horizons without IPOPT "
        "(the figures mean little)",
    )
    parser.add_argument(
        "--out",
        default=DEFAULT_OUT,
        help=(
            "JSON output (default: %(default)s); the Markdown table goes beside it (.md); "
            "both are checked writable before the benchmark runs"
        ),
    )
    parser.add_argument(
        "--no-compiled",
        action="store_true",
        help="leave out the compiled loop's plan agreement and the exported C controllers "
        "(built with make and timed from C); fast_c is still timed when among --solvers",
    )
    parser.add_argument(
        "--predictions",
        default=None,
        metavar="HORIZONS",
        help="run the closed-loop sweep alone, e.g. 7,15,30,50: the scenario agent (the "
        "config's solver) at each horizon N, with open-loop and feedback predictions "
        "(agents.prediction) and each iteration mode (agents.iterations, where it exists), "
        f"the first {CLOSED_LOOP_STEPS} steps (or --horizon-steps) of each of --seeds; "
        "prints median/p95/max per-step times (estimator + solve) and every failed step",
    )
    parser.add_argument(
        "--agent",
        default=CLOSED_LOOP_AGENT,
        help="the registered agent whose steps --predictions times (default: %(default)s)",
    )
    parser.add_argument(
        "--predictions-replay",
        default=None,
        metavar="HORIZONS",
        help="run the solver sweep alone: the fast solver on the open-loop and the feedback "
        "problem at each horizon N, drawn around the estimates of a closed loop at the "
        f"config's horizon ({PREDICTION_STEPS} per seed, or --horizon-steps); median/p95 "
        "solve times and every failed solve",
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")
    return parser


def _prediction_sweep(args: argparse.Namespace, seeds: list[int], out: Path) -> int:
    """``--predictions`` (the closed-loop sweep) or ``--predictions-replay`` (the solver
    sweep) alone, printed and written to ``out``."""
    if args.predictions is not None:
        result = closed_loop_steps(
            parse_ints(args.predictions, "predictions"),
            config=args.config or DEFAULT_PRESET,
            seeds=seeds,
            steps=args.horizon_steps or CLOSED_LOOP_STEPS,
            agent=args.agent,
            progress=not args.no_progress,
        )
        table = format_closed_loop(result)
    else:
        result = sweep_predictions(
            parse_ints(args.predictions_replay, "predictions-replay"),
            config=args.config or DEFAULT_PRESET,
            seeds=seeds,
            steps_per_seed=args.horizon_steps or PREDICTION_STEPS,
            progress=not args.no_progress,
        )
        table = format_predictions(result)
    print(table, flush=True)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(json_ready(result), indent=1, allow_nan=False) + "\n")
    out.with_suffix(".md").write_text("```\n" + table + "\n```\n")
    print(f"\nwrote {out} and {out.with_suffix('.md')}")
    return 0


def _solver_list(text: str, skip: Sequence[str]) -> list[str]:
    names = [s.strip() for s in text.split(",") if s.strip()]
    for name in names:
        if name not in SOLVERS:
            raise ValueError(f"solvers: unknown solver {name!r}; choose from {', '.join(SOLVERS)}")
    return [s for s in names if s not in skip]


@one_line_errors("lfm-benchmark")
def benchmark_main(argv: Sequence[str] | None = None) -> int:
    """Command line: run the benchmark, print the report, write JSON and Markdown; returns 0, or 1
    with ``--check`` when a check fails.
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    limit_blas_threads()  # the filter and the IPOPT references too, not only make_solver's
    try:
        seeds = parse_seeds(args.seeds or (QUICK["seeds"] if args.quick else "0:6"))
        default_solvers = QUICK_SOLVERS if args.quick else DEFAULT_SOLVERS
        solvers = _solver_list(args.solvers or ",".join(default_solvers), args.skip)
        horizons = parse_ints(args.horizons, "horizons")
        if args.predictions is not None:
            parse_ints(args.predictions, "predictions")
        if args.predictions_replay is not None:
            parse_ints(args.predictions_replay, "predictions-replay")
    except ValueError as exc:
        parser.error(str(exc))
    config_argument_path(parser, args.config)  # a preset's name or a file: exits 2 otherwise
    out = Path(args.out)
    for path in (out, out.with_suffix(".md")):  # before the work (minutes), not after it
        problem = check_writable(path, "--out")
        if problem is not None:
            parser.error(problem)
    if args.predictions is not None or args.predictions_replay is not None:
        return _prediction_sweep(args, seeds, out)
    options: dict[str, Any] = {}
    if args.quick:
        options = {k: v for k, v in QUICK.items() if k != "seeds"}
    if args.max_steps is not None:
        options["max_steps"] = args.max_steps
    if args.horizon_steps is not None:
        options["horizon_steps"] = args.horizon_steps
    options.setdefault("max_steps", DEFAULT_MAX_STEPS)
    results = run_benchmark(
        config=args.config or DEFAULT_PRESET,
        seeds=seeds,
        solvers=solvers,
        horizons=horizons,
        thresholds=dict(args.threshold),
        progress=not args.no_progress,
        compiled=not args.no_compiled,
        **options,
    )
    results["meta"]["argv"] = list(sys.argv[1:] if argv is None else argv)
    print(format_report(results), flush=True)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(json_ready(results), indent=1, allow_nan=False) + "\n")
    markdown = out.with_suffix(".md")
    markdown.write_text(format_markdown(results))
    print(f"\nwrote {out} and {markdown}; {results['meta']['total_time_s']:.0f} s in all")
    failed = failed_checks(results["checks"])
    if args.check and failed:
        print(f"--check: {len(failed)} check(s) FAIL: " + "; ".join(c["key"] for c in failed))
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(benchmark_main())
