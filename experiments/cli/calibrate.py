"""``lfm-calibrate``: learn the latent force's hyperparameters from calibration episodes
(:mod:`experiments.calibration`), on any registered world."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from experiments.calibration import (
    LEARNABLE,
    fit_latent_force,
    record_calibration_episodes,
    write_learned_config,
)
from experiments.cli.common import (
    add_config_argument,
    add_set_argument,
    check_writable,
    config_argument,
    one_line_errors,
)
from experiments.evaluation import parse_seeds


def _calibrate_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="lfm-calibrate",
        description=(
            "Drive calibration episodes with the nominal MPC (no latent force model) on the "
            "config's world, record the measured states and the applied inputs, and fit the "
            "latent force's variance [(force unit)^2] and lengthscale [s] by maximum "
            "likelihood: a Kalman filter on the states the force drives (found from the "
            "system's force gain df/dw) and the force's state-space GP. Writes a config "
            "whose agents model the learned force."
        ),
        epilog=(
            "examples:\n"
            "  lfm-calibrate --config paper --seeds 1000:1005 --out results/learned.yaml\n"
            "  lfm-calibrate --config paper --out results/learned.yaml --force   replace it\n"
            "  lfm-calibrate --config quadrotor --seeds 1000:1003\n"
            "  lfm-calibrate --config mine.yaml     a world of your own "
            "(env_id: mine:Mine/Unicycle-v0)"
        ),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_config_argument(parser)
    add_set_argument(parser)
    parser.add_argument(
        "--seeds",
        default="1000:1005",
        help="env seeds of the calibration episodes (default 1000:1005, apart from "
        "evaluation seeds)",
    )
    parser.add_argument(
        "--out",
        default=None,
        help="write the learned config here (YAML); an existing file is refused unless --force",
    )
    parser.add_argument("--force", action="store_true", help="replace an existing --out file")
    return parser


@one_line_errors("lfm-calibrate")
def calibrate_main(argv: Sequence[str] | None = None) -> int:
    """``lfm-calibrate``: learn the latent force's hyperparameters from calibration episodes (an
    unwritable ``--out``, or an existing one without ``--force``, is refused first).
    """
    parser = _calibrate_parser()
    args = parser.parse_args(argv)
    try:
        seeds = parse_seeds(args.seeds)
    except ValueError as exc:
        parser.error(" ".join(str(exc).split()))
    _, config = config_argument(parser, args, ["nominal"])
    if args.out:  # before the episodes, not after them
        problem = check_writable(args.out, "--out")
        if problem is None and Path(args.out).exists() and not args.force:
            problem = (
                f"--out {args.out}: the file exists (a learned config of an earlier run?); "
                "choose another name or pass --force to replace it"
            )
        if problem is not None:
            parser.error(problem)
    try:
        records = record_calibration_episodes(config, seeds)
        result = fit_latent_force(records, config.env)
    except ValueError as exc:  # a world whose force cannot be calibrated: one line
        parser.error(" ".join(str(exc).split()))
    print(
        f"calibration: {result.n_episodes} episodes, {result.n_samples} samples of "
        f"{', '.join(result.states)} on {config.env_id}"
    )
    print(f"{'hyperparameter':<14} {'learned':>10} {'std err (log)':>14} {'true (hidden)':>14}")
    for name in LEARNABLE:
        learned = getattr(result.latent_force, name)
        se = result.std_errors[name]
        print(f"{name:<14} {learned:>10.4g} {se:>14.3g} {result.true[name]:>14.4g}")
    if not result.success:
        print(f"warning: optimiser: {result.message}", file=sys.stderr)
    if args.out:
        write_learned_config(config, result, args.out)
        print(f"learned config: {args.out}")
    return 0
