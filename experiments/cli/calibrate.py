"""``lfm-calibrate``: learn the latent force's hyperparameters from calibration episodes
(:mod:`experiments.calibration`)."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from experiments.calibration import (
    LEARNABLE,
    fit_latent_force,
    record_calibration_episodes,
    write_learned_config,
)
from experiments.cli.common import check_writable, config_file, one_line_errors, preset_names
from experiments.evaluation import parse_seeds
from lfm_env.config import load_env_config


def _calibrate_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="lfm-calibrate",
        description=(
            "Drive calibration episodes with the nominal MPC (no latent force model), record "
            "measured speeds and applied accelerations, and fit the latent force's variance "
            "[(m/s^2)^2] and lengthscale [s] by maximum likelihood (Kalman filter on speed "
            "and latent state). Writes a config whose agents model the learned force."
        ),
        epilog="example: lfm-calibrate --config paper --seeds 100:105 --out results/learned.yaml",
    )
    parser.add_argument(
        "--config",
        metavar="NAME|YAML",
        default="paper",
        help=f"a preset's name ({', '.join(preset_names())}) or a config file (default: paper)",
    )
    parser.add_argument(
        "--seeds",
        default="1000:1005",
        help="env seeds of the calibration episodes (default 1000:1005, apart from "
        "evaluation seeds)",
    )
    parser.add_argument("--out", default=None, help="write the learned config here (YAML)")
    return parser


@one_line_errors("lfm-calibrate")
def calibrate_main(argv: Sequence[str] | None = None) -> int:
    """``lfm-calibrate``: learn the latent force's hyperparameters from calibration episodes.

    An unwritable ``--out`` is refused before the episodes run; operating-system errors
    give one line and exit code 2 (:func:`experiments.cli.one_line_errors`).
    """
    parser = _calibrate_parser()
    args = parser.parse_args(argv)
    try:
        seeds = parse_seeds(args.seeds)
        args.config = str(config_file(args.config))
        env_config = load_env_config(args.config)
    except ValueError as exc:
        parser.error(" ".join(str(exc).split()))
    if args.out:  # before the episodes, not after them
        problem = check_writable(args.out, "--out")
        if problem is not None:
            parser.error(problem)
    result = fit_latent_force(record_calibration_episodes(args.config, seeds), env_config)
    print(f"calibration: {result.n_episodes} episodes, {result.n_samples} samples")
    print(f"{'hyperparameter':<14} {'learned':>10} {'std err (log)':>14} {'true (hidden)':>14}")
    for name in LEARNABLE:
        learned = getattr(result.latent_force, name)
        se = result.std_errors[name]
        print(f"{name:<14} {learned:>10.4g} {se:>14.3g} {result.true[name]:>14.4g}")
    if not result.success:
        print(f"warning: optimiser: {result.message}", file=sys.stderr)
    if args.out:
        write_learned_config(args.config, result, args.out)
        print(f"learned config: {args.out}")
    return 0


__all__ = ["calibrate_main"]
