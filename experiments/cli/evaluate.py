"""``lfm-evaluate``: agents over seeds on one config, into a resumable results folder."""

from __future__ import annotations

import argparse
import sys
import textwrap
from collections.abc import Sequence
from pathlib import Path

from experiments.cli.common import (
    CACHE_NOTE,
    add_config_argument,
    add_episode_timeout_argument,
    add_executor_arguments,
    add_set_argument,
    config_argument,
    one_line_errors,
    registered_agents_help,
    run_episodes,
    seeds_and_executor,
)

_EVALUATE_EPILOG = """\
files written (DIR is --out):
  DIR/config.yaml                       the resolved config of every episode in DIR
  DIR/episodes/<agent>__seed<S>.npz     trajectory of one episode
  DIR/episodes/<agent>__seed<S>.json    its row of metrics (written last: marks it done)
  DIR/episodes.csv                      all rows, sorted by agent and seed

A config file may start with "base: paper" (a preset's name, or a path relative to
the file) and override only some fields; --set KEY=VALUE overrides one more (DIR's
config.yaml records the resolved config). A world of your own is named in the config
as env_id: your.module:Name-v0 (the module, which calls lfm_env.register_world, is
imported first; from the current folder too).

Rerunning the same command resumes an interrupted run: finished episodes are
skipped and episodes that raised an error are retried. A folder holds one config;
resuming with another config is refused; one run writes into a folder at a time.
An episode that raises (SystemExit included), runs past --episode-timeout, or whose
worker process dies (--jobs) is an error row naming why; the other episodes run on.
Exit code 0 when every episode ran, 1 when some raised (they are in the table with
their error), 2 on bad arguments or when the report failed (one line on stderr; the
results are kept), 130 when interrupted.

Metrics (columns of episodes.csv): success, steps, time_to_goal [s], cost (sum of
the true stage cost), then per constraint group G of the world's system
<G>_violation_steps and max_<G>_excess [the group's unit] (sine track: track [m],
x [m], speed [m/s]; quadrotor: corridor [m], x [m]) and <G>_violation_steps_over_<T>
per tolerance T of the group (steps with the excess above T; sine track: track and x
0.01, 0.05 m, speed 0.05 m/s), failure (the env ended the
episode as a failure), latent_rmse [force unit] and latent_coverage (2-sigma band;
filter agents only), solve_time_median/p95/max [s], solver_failures (steps whose
solve gave no usable plan), unconverged_solves (steps that applied the usable plan
of a solve that did not converge), fallback_steps, filter_resets, slack_total,
wall_time [s], error.

examples:
  lfm-evaluate                                   paper config, seeds 0:20, 3 agents
  lfm-evaluate --config quick --seeds 0:5 --jobs 2      a preset, by name
  lfm-evaluate --config quadrotor --agents nominal,scenario,oracle
  lfm-evaluate --config my/config.yaml --seeds 0:5      a config file, by path
  lfm-evaluate --config paper --set agents.horizon=10 --set env.latent_force.variance=2.0
  lfm-evaluate --agents scenario,oracle --seeds 0:10,20:25 --out results/sweep
  lfm-evaluate --agents nominal,mypkg.agents:MyAgent   your own agent next to nominal
  lfm-evaluate --dask-workers 2                  local Dask cluster on 127.0.0.1
  lfm-evaluate --scheduler tcp://10.0.0.5:8786   existing Dask cluster (DIR shared)
"""


def _evaluate_parser() -> argparse.ArgumentParser:
    agents_help = registered_agents_help()
    parser = argparse.ArgumentParser(
        prog="lfm-evaluate",
        description=(
            "Run MPC agents on the world of the config (its env_id, e.g. lfm_env/SineTrack-v0\n"
            "for configs/paper.yaml) over env seeds and save one row of metrics and one\n"
            "trajectory per episode. For one env seed every agent faces the same hidden\n"
            "latent_force and noise (paired design)."
        ),
        epilog=_EVALUATE_EPILOG + "\n" + textwrap.fill(CACHE_NOTE, 84) + "\n",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_config_argument(parser)
    add_set_argument(parser)
    parser.add_argument(
        "--agents",
        default="nominal,pf,scenario",
        metavar="A,B,...",
        help=(
            "comma-separated agents (default: nominal,pf,scenario): registered names, or "
            "your own agent as module:attribute, a factory called with the resolved config "
            "(or an agent class taking it) returning an object with reset(seed=None) and "
            "act(obs) (docs/own-system.md, 'Your own agent'; the module is looked up from the "
            f"current folder too). {agents_help}"
        ),
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
    add_executor_arguments(parser, "local worker processes (default: 1, serial)")
    add_episode_timeout_argument(parser)
    parser.add_argument(
        "--out",
        metavar="DIR",
        default=None,
        help="results folder (default: results/<config file stem>, e.g. results/paper)",
    )
    parser.add_argument(
        "--no-report",
        action="store_true",
        help="do not write the report after the run (default: experiments.report.write_report)",
    )
    parser.add_argument(
        "--baseline",
        metavar="NAME",
        default=None,
        help=(
            "the agent of --agents that every paired table of the report compares the "
            "others with (default: robust if run, else scenario, else the first agent)"
        ),
    )
    parser.add_argument(
        "--quiet", action="store_true", help="no progress bar and no per-agent summary"
    )
    return parser


def _print_summary(rows: list[dict]) -> None:
    """One line per agent: episodes, successes, failures, errors."""
    agents = list(dict.fromkeys(r["agent"] for r in rows))
    width = max((len(a) for a in agents), default=0)
    for agent in agents:
        mine = [r for r in rows if r["agent"] == agent]
        ok = [r for r in mine if r["error"] == ""]
        print(
            f"  {agent:>{width}}: {len(mine)} episodes, "
            f"{sum(r['success'] for r in ok)} reached the goal, "
            f"{sum(r['failure'] for r in ok)} left the safety box, "
            f"{len(mine) - len(ok)} raised an error"
        )


@one_line_errors("lfm-evaluate")
def evaluate_main(argv: Sequence[str] | None = None) -> int:
    """``lfm-evaluate``: evaluate agents over seeds and write the results; exit code 0 if every
    episode ran, 1 if some raised, 2 if the report failed (the results are kept).
    """
    from experiments.evaluation import evaluate

    parser = _evaluate_parser()
    args = parser.parse_args(argv)

    seeds = seeds_and_executor(parser, args)
    # (a module:attribute agent's module is found in the working folder too, last: by name)
    agents = [a.strip() for a in args.agents.split(",")]
    if args.baseline is not None and args.baseline not in agents:
        parser.error(f"--baseline {args.baseline!r}: not among --agents ({', '.join(agents)})")
    config_path, config = config_argument(parser, args)
    out = (
        Path(args.out)
        if args.out
        else Path("results") / (config_path.stem if config_path is not None else "defaults")
    )

    rows = run_episodes(
        parser,
        args,
        out,
        evaluate,
        agents,
        seeds,
        config=config,
        episode_timeout=args.episode_timeout,
    )
    if rows is None:
        return 130
    n_errors = sum(r["error"] != "" for r in rows)
    if not args.quiet:
        _print_summary(rows)
    print(f"results: {out / 'episodes.csv'} ({len(rows)} episodes, {n_errors} with errors)")
    if n_errors:
        print(f"rerun the same command to retry the {n_errors} episodes that raised an error")

    if not args.no_report:
        try:
            from experiments.report import write_report
        except ImportError as exc:
            print(f"report: skipped, experiments.report is not available ({exc})")
        else:
            try:
                where = write_report(out, baseline=args.baseline)
            except Exception as exc:  # the results are safe; only the report failed
                reason = " ".join(f"{type(exc).__name__}: {exc}".split())
                print(
                    f"lfm-evaluate: error: the report failed ({reason}); the results are kept "
                    f"in {out} (lfm-report {out} writes the report again)",
                    file=sys.stderr,
                )
                return 2
            print(f"report: {where if where is not None else out}")
    return 1 if n_errors else 0
