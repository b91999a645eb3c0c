"""``lfm-train``: train the RL baseline on the config's world and save its policy
(:mod:`experiments.rl_training`)."""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from pathlib import Path

from controllers.config import load_config
from experiments.cli.common import (
    add_config_argument,
    add_set_argument,
    check_writable,
    config_argument_path,
    one_line_errors,
)
from experiments.evaluation.storage import ResultsFolderError
from experiments.rl_training import (
    ALGOS,
    DEFAULT_N_ENVS,
    EVAL_CONFIG_FILE,
    POLICY_FILE,
    check_training_arguments,
    train,
)


def _train_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="lfm-train",
        description=(
            "Train an RL baseline (stable-baselines3 PPO or SAC) on the config's world "
            "through gym.make; saves OUT/policy.zip for the 'rl' agent and OUT/eval.yaml, the "
            "training's config with agents.rl_policy set, which evaluates it: lfm-evaluate "
            "--config OUT/eval.yaml --agents rl,nominal,scenario. Training stops after "
            "--timesteps steps or --minutes minutes, whichever comes first."
        ),
        epilog="One run owns OUT at a time; a folder that holds a policy is refused unless "
        "--resume (train it further) or --force (replace it) is given. Exit code 0 when the "
        "policy is saved, 2 on bad arguments or a folder that is refused. "
        "example (the README's run): lfm-train --config paper --algo ppo --minutes 28 "
        "--n-envs 8 --seed 0 --out results/rl/ppo_paper",
    )
    add_config_argument(parser)
    add_set_argument(parser)
    parser.add_argument("--algo", choices=ALGOS, default="ppo", help="algorithm (default ppo)")
    parser.add_argument(
        "--timesteps",
        type=int,
        default=1_000_000,
        help="env steps at most, summed over the envs (default 1e6)",
    )
    parser.add_argument(
        "--minutes",
        type=float,
        default=None,
        help="wall-clock budget [min] that stops training earlier (default: none, the "
        "--timesteps cap alone)",
    )
    parser.add_argument("--out", default="results/rl/ppo", help="output folder")
    parser.add_argument("--seed", type=int, default=0, help="seed (default 0)")
    parser.add_argument(
        "--n-envs",
        type=int,
        default=DEFAULT_N_ENVS,
        help=f"envs stepped in lockstep in one process (default {DEFAULT_N_ENVS})",
    )
    parser.add_argument(
        "--cost-weight",
        type=float,
        default=1.0,
        help="training penalty per violated constraint group and step (default 1)",
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    again = parser.add_mutually_exclusive_group()
    again.add_argument(
        "--resume",
        action="store_true",
        help="train the policy in OUT further, for --timesteps more steps (its algorithm "
        "and world must match)",
    )
    again.add_argument(
        "--force", action="store_true", help="replace the policy in OUT (default: refuse)"
    )
    return parser


@one_line_errors("lfm-train")
def train_main(argv: Sequence[str] | None = None) -> int:
    """``lfm-train``: train and save a policy; prints the run's summary as JSON."""
    parser = _train_parser()
    args = parser.parse_args(argv)
    path = config_argument_path(parser, args.config)
    try:
        check_training_arguments(
            args.algo, args.timesteps, args.minutes, args.n_envs, args.cost_weight
        )
        config = load_config(path, args.overrides)
    except ValueError as exc:
        parser.error(" ".join(str(exc).split()))
    for name in (POLICY_FILE, EVAL_CONFIG_FILE):  # before the training, not after it
        problem = check_writable(Path(args.out) / name, "--out")
        if problem is not None:
            parser.error(problem)
    try:
        summary = train(
            config,
            algo=args.algo,
            timesteps=args.timesteps,
            minutes=args.minutes,
            out=args.out,
            seed=args.seed,
            n_envs=args.n_envs,
            cost_weight=args.cost_weight,
            progress=not args.no_progress,
            resume=args.resume,
            force=args.force,
        )
    except ResultsFolderError as exc:  # refused before any training
        parser.error(" ".join(str(exc).split()))
    print(json.dumps(summary, indent=2))
    print(f"policy: {Path(args.out) / POLICY_FILE}")
    print(
        f"evaluate it: lfm-evaluate --config {Path(args.out) / EVAL_CONFIG_FILE} "
        "--agents rl,nominal,scenario"
    )
    return 0
