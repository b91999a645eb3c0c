"""``lfm-render``: an episode drawn on the highway-env road, as a GIF or frames."""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path

from experiments.cli.common import (
    add_config_argument,
    add_set_argument,
    check_writable,
    config_argument,
    one_line_errors,
    positive_int,
    registered_agents_help,
)

_RENDER_EPILOG = """\
Runs ONE episode (the same one lfm-evaluate runs for this agent, config and seed: the
agent's own seed is derived the same way) on the config's world and draws every step
with that world's own renderer (render_mode="rgb_array", no display needed); a world
without a scene of its own gets the report's plan panel (a camera on the first two
states with the estimate and the plan's scenario fan). A .gif
gets one frame per step plus the start (1/dt frames per second); a .png gets one frame.
To look at a saved episode without re-running it, use lfm-report (figures/episode.gif).

examples:
  lfm-render --agent scenario --seed 0 --out scenario.gif
  lfm-render --config configs/quick.yaml --agent pf --seed 3 --steps 40 --out pf.png
  lfm-render --config configs/quadrotor.yaml --agent scenario --out quadrotor.gif
  lfm-render --config quick --set env.latent_force.variance=9.0 --agent pf --out pf.gif
"""


def _render_parser() -> argparse.ArgumentParser:
    agents_help = registered_agents_help()
    parser = argparse.ArgumentParser(
        prog="lfm-render",
        description="Run one episode of an agent on the config's world and render it.",
        epilog=_RENDER_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_config_argument(parser)
    add_set_argument(parser)
    parser.add_argument(
        "--agent", default="scenario", help=f"agent (default: scenario). {agents_help}"
    )
    parser.add_argument("--seed", type=int, default=0, metavar="S", help="env seed (default: 0)")
    parser.add_argument(
        "--out", required=True, metavar="FILE", help="output file, .gif (animation) or .png"
    )
    parser.add_argument(
        "--steps",
        type=positive_int,
        default=None,
        metavar="N",
        help="stop after N steps (default: run until the episode ends)",
    )
    parser.add_argument(
        "--frame",
        choices=("last", "first"),
        default="last",
        help="which frame a .png gets (default: last)",
    )
    parser.add_argument(
        "--size",
        default="480x240",
        metavar="WxH",
        help="frame size in pixels, for worlds whose renderer takes one (default: 480x240)",
    )
    return parser


def _panel_episode(
    cfg: object, agent_name: str, seed: int, max_steps: int | None, size: tuple[int, int]
) -> tuple[list, float]:
    """Frames of one episode of a world without a scene of its own: the plan's panel (a
    camera on the first two states with the estimate and the scenario fan), as the report's
    replay draws it."""
    from experiments.evaluation.run import run_episode
    from experiments.plots.episode import annotate_frame, plan_panel_frames
    from experiments.report.figures import world_goal

    _, traj = run_episode(agent_name, cfg, seed)
    goal_state, goal_radius = world_goal(cfg.env)
    panels = plan_panel_frames(
        cfg.make_system(), traj, size=size, goal_state=goal_state, goal_radius=goal_radius
    )
    if max_steps is not None:
        panels = panels[: max_steps + 1]
    dt = cfg.env.dt
    return [
        annotate_frame(p, f"{agent_name} | seed {seed} | t = {k * dt:.1f} s")
        for k, p in enumerate(panels)
    ], dt


def _render_episode(
    config: object, agent_name: str, seed: int, max_steps: int | None, size: tuple[int, int]
) -> tuple[list, float]:
    """Frames ``(H, W, 3)`` of one episode rendered step by step, and ``dt`` [s]."""
    from controllers.agents import agent_spec
    from experiments.evaluation.run import agent_seed, resolve_config
    from experiments.plots.replay import annotate_frame, make_render_env, world_draws

    cfg = resolve_config(config, [agent_name])
    if not world_draws(cfg):
        return _panel_episode(cfg, agent_name, seed, max_steps, size)
    # The same drawing options as the report's replay (experiments.plots.replay.replay_frames).
    env = make_render_env(cfg, screen_size=size)  # each world's own view
    try:
        spec = agent_spec(agent_name)
        agent = spec.build(cfg, env=env if spec.reads_truth else None)
        dt = env.unwrapped.model.dt
        obs, info = env.reset(seed=seed)
        agent.reset(seed=agent_seed(seed, agent_name))
        frames, k = [], 0

        def grab() -> None:
            text = f"{agent_name} | seed {seed} | t = {k * dt:.1f} s"
            frames.append(annotate_frame(env.render(), text))

        grab()
        done = False
        while not done and (max_steps is None or k < max_steps):
            obs, _, terminated, truncated, info = env.step(agent.act(obs))
            k += 1
            done = terminated or truncated
            grab()
    finally:
        env.close()
    return frames, dt


#: Largest frame side of lfm-render [px], and the memory budget of all its frames [bytes]
#: (the frames of a whole episode are kept until the GIF is written).
MAX_RENDER_SIDE = 4096
RENDER_MEMORY_BUDGET = 2 * 1024**3


@one_line_errors("lfm-render")
def render_main(argv: Sequence[str] | None = None) -> int:
    """``lfm-render``: run one episode and write it as a GIF or PNG; 0 when written."""
    from controllers.agents import AGENT_REGISTRY
    from experiments.plots import write_gif

    parser = _render_parser()
    args = parser.parse_args(argv)
    out = Path(args.out)
    if out.suffix.lower() not in (".gif", ".png"):
        parser.error(f"--out {args.out}: must end in .gif or .png")
    if args.agent not in AGENT_REGISTRY:
        parser.error(f"--agent {args.agent}: choose one of {', '.join(AGENT_REGISTRY)}")
    if args.seed < 0:
        parser.error(f"--seed {args.seed}: must be >= 0")
    try:
        width, height = (int(v) for v in args.size.lower().split("x"))
        if not (16 <= width <= MAX_RENDER_SIDE and 16 <= height <= MAX_RENDER_SIDE):
            raise ValueError
    except ValueError:
        parser.error(
            f"--size {args.size[:40]}: expected WxH in pixels, each >= 16 and <= {MAX_RENDER_SIDE},"
            " e.g. 480x240"
        )
    _, config = config_argument(parser, args, [args.agent])
    max_steps = config.env.max_steps
    n_frames = 1 + (max_steps if args.steps is None else min(args.steps, max_steps))
    need = 3 * width * height * n_frames
    if need > RENDER_MEMORY_BUDGET:
        parser.error(
            f"--size {width}x{height}: {n_frames} frames would need {need / 1024**3:.3g} GB,"
            f" over the budget of {RENDER_MEMORY_BUDGET / 1024**3:.3g} GB; use a smaller"
            " --size or fewer --steps"
        )
    problem = check_writable(out, "--out")
    if problem is not None:
        parser.error(problem)

    try:
        frames, dt = _render_episode(config, args.agent, args.seed, args.steps, (width, height))
    except ValueError as exc:  # a bad config: the loaders name the key
        parser.error(" ".join(str(exc).split()))
    if out.suffix.lower() == ".gif":
        write_gif(frames, out, fps=1.0 / dt)
    else:
        import imageio.v3 as iio

        iio.imwrite(out, frames[-1] if args.frame == "last" else frames[0])
    print(f"{out}: {len(frames)} frame(s), {len(frames) - 1} step(s) of {args.agent}")
    return 0
