"""Command lines of the project: thin layers that parse arguments and call library functions.

Each command is a ``<name>_main(argv=None) -> int`` function registered as a console
script in ``pyproject.toml`` (``lfm-evaluate = "controllers.cli:evaluate_main"``) and
wrapped by a one-line script in ``scripts/``. Bad arguments exit with code 2 and a
one-line message (``argparse``'s ``parser.error``).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

import controllers

# configs/ next to the package (a source checkout or an editable install).
_REPO_CONFIGS = Path(controllers.__file__).resolve().parent.parent / "configs"

_EVALUATE_EPILOG = """\
files written (DIR is --out):
  DIR/config.yaml                       the resolved config of every episode in DIR
  DIR/episodes/<agent>__seed<S>.npz     trajectory of one episode
  DIR/episodes/<agent>__seed<S>.json    its row of metrics (written last: marks it done)
  DIR/episodes.csv                      all rows, sorted by agent and seed

Rerunning the same command resumes an interrupted run: finished episodes are
skipped and episodes that raised an error are retried. A folder holds one config;
resuming with another config is refused. Exit code 0 when every episode ran, 1 when
some raised (they are in the table with their error), 2 on bad arguments.

Metrics (columns of episodes.csv): success, steps, time_to_goal [s], cost (sum of
the true stage cost), track/speed violation steps and largest excess [m, m/s],
max_x_excess [m], failure (left the safety box), latent_rmse [m/s^2] and
latent_coverage (2-sigma band; filter agents only), solve_time_median/p95/max [s],
solver_failures, fallback_steps, slack_total, wall_time [s], error.

examples:
  lfm-evaluate                                   paper config, seeds 0:20, 3 agents
  lfm-evaluate --config configs/quick.yaml --seeds 0:5 --jobs 2
  lfm-evaluate --agents scenario,oracle --seeds 0:10,20:25 --out results/sweep
  lfm-evaluate --dask-workers 2                  local Dask cluster on 127.0.0.1
  lfm-evaluate --scheduler tcp://10.0.0.5:8786   existing Dask cluster (DIR shared)
"""


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text!r} must be >= 1")
    return value


def _evaluate_parser() -> argparse.ArgumentParser:
    from controllers.agents import AGENT_LABELS

    agents_help = "; ".join(f"{k} = {v}" for k, v in AGENT_LABELS.items())
    default_config = _REPO_CONFIGS / "paper.yaml"
    parser = argparse.ArgumentParser(
        prog="lfm-evaluate",
        description=(
            "Run MPC agents on the SineTrack world (lfm_env/SineTrack-v0) over env seeds and\n"
            "save one row of metrics and one trajectory per episode. For one env seed every\n"
            "agent faces the same hidden disturbance and noise (paired design)."
        ),
        epilog=_EVALUATE_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "--config",
        metavar="YAML",
        default=None,
        help=(
            "config file with env and agents sections (default: "
            f"{default_config} if present, else the built-in paper defaults)"
        ),
    )
    parser.add_argument(
        "--agents",
        default="nominal,pf,scenario",
        metavar="A,B,...",
        help=f"comma-separated agents (default: nominal,pf,scenario). {agents_help}",
    )
    parser.add_argument(
        "--seeds",
        default="0:20",
        metavar="SEEDS",
        help=(
            "env seeds: a range start:end (end exclusive), single seeds and lists, "
            "e.g. 0:20, 3, 1,5,9, 0:10,20:25 (default: 0:20)"
        ),
    )
    parser.add_argument(
        "--jobs",
        type=_positive_int,
        default=1,
        metavar="N",
        help="local worker processes (default: 1, serial)",
    )
    parser.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        default=None,
        help="run on an existing Dask cluster, e.g. tcp://127.0.0.1:8786 (DIR must be shared)",
    )
    parser.add_argument(
        "--dask-workers",
        type=_positive_int,
        default=None,
        metavar="N",
        help="start a local Dask cluster of N single-threaded workers on 127.0.0.1",
    )
    parser.add_argument(
        "--out",
        metavar="DIR",
        default=None,
        help="results folder (default: results/<config file stem>, e.g. results/paper)",
    )
    parser.add_argument(
        "--no-report",
        action="store_true",
        help="do not write the report after the run (default: controllers.report.write_report)",
    )
    parser.add_argument(
        "--quiet", action="store_true", help="no progress bar and no per-agent summary"
    )
    return parser


def _print_summary(rows: list[dict]) -> None:
    """One line per agent: episodes, successes, failures, errors."""
    for agent in dict.fromkeys(r["agent"] for r in rows):
        mine = [r for r in rows if r["agent"] == agent]
        ok = [r for r in mine if r["error"] == ""]
        print(
            f"  {agent:>9}: {len(mine)} episodes, {sum(r['success'] for r in ok)} reached the "
            f"goal, {sum(r['failure'] for r in ok)} left the safety box, "
            f"{len(mine) - len(ok)} raised an error"
        )


def evaluate_main(argv: Sequence[str] | None = None) -> int:
    """``lfm-evaluate``: evaluate agents over seeds and write the results (see ``--help``).

    Returns:
        The exit code: 0 if every episode ran, 1 if some raised an error.
    """
    from controllers.evaluation import evaluate, parse_seeds

    parser = _evaluate_parser()
    args = parser.parse_args(argv)

    if args.config is None:
        default = _REPO_CONFIGS / "paper.yaml"
        config_path = default if default.is_file() else None
    else:
        config_path = Path(args.config)
        if not config_path.is_file():
            parser.error(f"--config {args.config}: no such file")
    try:
        seeds = parse_seeds(args.seeds)
    except ValueError as exc:
        parser.error(f"--seeds: {exc}")
    if args.scheduler is not None and args.dask_workers is not None:
        parser.error("--scheduler and --dask-workers exclude each other")
    if args.jobs > 1 and (args.scheduler is not None or args.dask_workers is not None):
        parser.error("--jobs runs local processes; do not combine it with Dask options")
    agents = [a.strip() for a in args.agents.split(",")]
    out = (
        Path(args.out)
        if args.out
        else Path("results") / (config_path.stem if config_path is not None else "defaults")
    )

    try:
        rows = evaluate(
            agents,
            seeds,
            config=config_path,
            out=out,
            jobs=args.jobs,
            scheduler=args.scheduler,
            dask_workers=args.dask_workers,
            progress=not args.quiet,
        )
    except (ValueError, ConnectionError) as exc:  # raised before any episode runs
        parser.error(" ".join(str(exc).split()))
    except KeyboardInterrupt:
        print(f"\ninterrupted; finished episodes are in {out}; rerun to resume", file=sys.stderr)
        return 130

    n_errors = sum(r["error"] != "" for r in rows)
    if not args.quiet:
        _print_summary(rows)
    print(f"results: {out / 'episodes.csv'} ({len(rows)} episodes, {n_errors} with errors)")
    if n_errors:
        print(f"rerun the same command to retry the {n_errors} episodes that raised an error")

    if not args.no_report:
        try:
            from controllers.report import write_report
        except ImportError as exc:
            print(f"report: skipped, controllers.report is not available ({exc})")
        else:
            try:
                where = write_report(out)
            except Exception as exc:  # the results are safe; only the report failed
                print(f"report: failed ({type(exc).__name__}: {exc}); results are kept")
                return 1
            print(f"report: {where if where is not None else out}")
    return 1 if n_errors else 0
