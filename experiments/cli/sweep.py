"""``lfm-sweep``: the risk trade-off sweep over constraint back-offs."""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path

from experiments.cli.common import (
    add_config_argument,
    add_episode_timeout_argument,
    add_executor_arguments,
    config_argument_path,
    one_line_errors,
    registered_agents_help,
    run_episodes,
    seeds_and_executor,
)

_SWEEP_EPILOG = """\
files written (DIR is --out):
  DIR/sweep.json                  what is swept: agent, key, values, baseline, seeds
  DIR/baseline/                   the baseline agent on the base config (lfm-evaluate folder)
  DIR/<KEY>=<VALUE>/              the agent with KEY set to VALUE, one folder per value
  DIR/sweep.md                    the table: per value its mean and the paired difference
                                  to the baseline with a 95% bootstrap interval
  DIR/sweep.png                   the Pareto picture: violation steps beyond the first
                                  tolerance against time to goal, paired to the baseline

--set takes a dotted key of the agents section and comma-separated values, read by
the key's own type (a list key takes one value or [a,b,...]; null where allowed):
agents.backoff, agents.n_scenarios, agents.estimator, agents.n_particles,
agents.robust.backoff, ... Rerunning the same command resumes an interrupted sweep
(finished episodes are kept). lfm-report RESULTS --sweep DIR puts the table and the
figure into a report. Exit code 0 when every episode ran, 1 when some raised, 2 on
bad arguments.

examples:
  lfm-sweep --config configs/paper.yaml --agent robust --set agents.robust.backoff=0,1,2,3 \\
            --baseline pf --seeds 0:100 --jobs 2 --out results/sweep
  lfm-sweep --config configs/quick.yaml --agent scenario --set agents.backoff=0,2 --seeds 0:5
  lfm-sweep --agent robust --set agents.robust.estimator=bootstrap,rbpf,ukf --seeds 0:20
"""


def _sweep_parser() -> argparse.ArgumentParser:
    agents_help = registered_agents_help()
    parser = argparse.ArgumentParser(
        prog="lfm-sweep",
        description=(
            "The risk trade-off: run one agent with one setting swept over values, and a\n"
            "baseline agent once, on the same env seeds (same hidden latent force and noise),\n"
            "then compare each value with the baseline: violation steps beyond each tolerance,\n"
            "zero-violation episodes and time to goal, with paired bootstrap intervals."
        ),
        epilog=_SWEEP_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_config_argument(parser)
    parser.add_argument(
        "--agent", default="robust", help=f"the agent swept (default: robust). {agents_help}"
    )
    parser.add_argument(
        "--set",
        dest="setting",
        required=True,
        metavar="KEY=V1,V2,...",
        help="the swept setting, e.g. agents.robust.backoff=0,1,2,3",
    )
    parser.add_argument(
        "--baseline", default="pf", help="the agent every value is compared with (default: pf)"
    )
    parser.add_argument(
        "--seeds",
        default="0:20",
        metavar="SEEDS",
        help="env seeds, e.g. 0:100, 3, 1,5,9 (end exclusive; default: 0:20)",
    )
    add_executor_arguments(parser, "local worker processes per evaluation (default: 1, serial)")
    add_episode_timeout_argument(parser)
    parser.add_argument(
        "--out",
        metavar="DIR",
        default="results/sweep",
        help="sweep folder (default: results/sweep)",
    )
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    return parser


@one_line_errors("lfm-sweep")
def sweep_main(argv: Sequence[str] | None = None) -> int:
    """``lfm-sweep``: sweep one agent setting against a baseline; 0 if every episode ran, else 1."""
    from experiments.report.sweep_summary import sweep_errors
    from experiments.sweep import run_sweep

    parser = _sweep_parser()
    args = parser.parse_args(argv)
    config_path = config_argument_path(parser, args.config)
    seeds = seeds_and_executor(parser, args)
    out = Path(args.out)
    summary = run_episodes(
        parser,
        args,
        out,
        run_sweep,
        args.agent.strip(),
        args.setting,
        seeds,
        config=config_path,
        baseline=args.baseline.strip(),
        episode_timeout=args.episode_timeout,
    )
    if summary is None:
        return 130
    n_errors = sweep_errors(summary)
    print(f"sweep: {out / 'sweep.md'} and {out / 'sweep.png'} ({len(summary.values)} values)")
    if n_errors:
        print(f"{n_errors} episodes raised an error; rerun the same command to retry them")
    return 1 if n_errors else 0
