"""``lfm-report``: the baseline-comparison report of a results folder."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from experiments.cli.common import check_writable, one_line_errors

_REPORT_EPILOG = """\
files written (DIR is the results folder):
  DIR/report.md, DIR/report.html   the same report; report.md links the figures,
                                   report.html embeds them all (it can be sent alone)
  DIR/figures/*.png                figures of one episode (with the plan's scenario fan
                                   at four steps), across-seed plots
  DIR/figures/episode.gif          the episode replayed from its saved true states, with
                                   the estimate and the scenario fan below the scene
  DIR/figures/estimator_coverage.png      coverage and RMSE of the filtering agents
  DIR/figures/sweep.png            the risk sweep's Pareto picture (with --sweep, or
                                   when DIR holds a sweep.md of lfm-sweep)

Reads DIR/episodes.csv, DIR/episodes/*.npz and DIR/config.yaml; runs no episode.
The figures and the metric units come from the system of the world in config.yaml,
so a results folder of any world (configs/paper.yaml, configs/quadrotor.yaml, ...)
is reported the same way.
Claims about intervals over fewer than 20 seeds carry a caveat; the settings paragraph
names only the settings of the agents DIR holds.
Exit code 0 on success (and, with one line and no report, on a folder whose run has
finished no episode yet), 2 when DIR is missing, empty or the seed has no trajectory, or
when the sweep ran on another config (without --allow-other-config).

examples:
  lfm-report results/paper
  lfm-report results/quick --seed 3 --no-gif
  lfm-report results/paper --sweep results/sweep
  lfm-report results/paper --sweep results/quick_sweep --allow-other-config
  lfm-report results/paper --baseline pf         paired differences against pf
"""


def _report_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="lfm-report",
        description=(
            "Write report.md and report.html for a results folder of lfm-evaluate: per-agent\n"
            "means with 95% BCa bootstrap intervals (scipy.stats.bootstrap; constraint metrics\n"
            "per group of the world's system), paired differences against a baseline agent\n"
            "(paired bootstrap), one episode's figures\n"
            "drawn from the system (path in the plane of the first two states with the\n"
            "feasible region, latent force, inputs with bounds, other states, constraint\n"
            "excess), across-seed plots, a GIF of the episode and, for the sine track, a\n"
            "'paper vs measured' table. The oracle agent is certainty-equivalent MPC that\n"
            "reads the hidden truth (labelled so); it is no upper bound."
        ),
        epilog=_REPORT_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("results_dir", metavar="DIR", help="results folder of lfm-evaluate")
    parser.add_argument(
        "--seed",
        type=int,
        default=None,
        metavar="S",
        help=(
            "env seed of the episode figures and GIF (default: the smallest seed whose "
            "scenario episode ran without error for at least one step)"
        ),
    )
    parser.add_argument("--no-gif", action="store_true", help="do not write figures/episode.gif")
    parser.add_argument(
        "--baseline",
        metavar="NAME",
        default=None,
        help=(
            "the agent that every paired table of the report compares the other agents with "
            "(default: robust if DIR holds it, else scenario, else the first agent)"
        ),
    )
    parser.add_argument(
        "--sweep",
        metavar="SWEEPDIR",
        default=None,
        help=(
            "include the table and Pareto figure of an lfm-sweep folder (default: DIR's own "
            "sweep when DIR holds a sweep.md); a sweep run on another config than DIR's is "
            "refused, naming the fields that differ"
        ),
    )
    parser.add_argument(
        "--allow-other-config",
        action="store_true",
        help=(
            "include a sweep run on another config than DIR's anyway; the report then lists "
            "the fields that differ beside the sweep's table"
        ),
    )
    return parser


def _nothing_to_report_yet(folder: Path) -> str | None:
    """What to say when ``folder`` is taken by a run that has finished no episode yet (its
    first seconds: the lock held, no episode record); ``None`` otherwise."""
    from experiments.evaluation.storage import folder_in_use

    if not folder.is_dir():
        return None
    owner = folder_in_use(folder)
    if owner is None or any((folder / "episodes").glob("*.json")):
        return None
    return (
        f"results folder {str(folder)!r} is being written by {owner} and holds no finished "
        "episode yet; nothing to report (run lfm-report again once episodes are finished)"
    )


@one_line_errors("lfm-report")
def report_main(argv: Sequence[str] | None = None) -> int:
    """``lfm-report``: write the report of a results folder; 0 when written."""
    from experiments.report import write_report

    parser = _report_parser()
    args = parser.parse_args(argv)
    folder = Path(args.results_dir)
    if folder.is_dir():  # the report's files: writable before any figure is drawn
        figures = folder / "figures"
        problem = check_writable(folder / "report.md", "DIR")
        if problem is None and figures.exists() and not figures.is_dir():
            problem = f"DIR {figures}: is a file, expected the report's figures folder"
        if problem is not None:
            parser.error(problem)
    busy = _nothing_to_report_yet(folder)
    if busy is not None:
        print(f"lfm-report: {busy}", file=sys.stderr)
        return 0
    try:
        path = write_report(
            args.results_dir,
            figure_seed=args.seed,
            gif=not args.no_gif,
            sweep_dir=args.sweep,
            baseline=args.baseline,
            allow_other_config=args.allow_other_config,
        )
    except (FileNotFoundError, ValueError) as exc:
        parser.error(" ".join(str(exc).split()))
    print(f"report: {path} and {path.with_suffix('.html')}")
    return 0
