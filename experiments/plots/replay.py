"""Replays of saved episodes: saved true states drawn by each world's own scene
(:meth:`lfm_env.env.LatentForceEnv.make_scene`), captions, GIFs.
"""

from __future__ import annotations

import inspect
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np


def annotate_frame(frame: np.ndarray, text: str) -> np.ndarray:
    """A copy of an RGB ``frame`` with ``text`` in its top-left corner (which also keeps
    consecutive frames distinct, so a GIF writer does not merge them).
    """
    from PIL import Image, ImageDraw

    image = Image.fromarray(np.ascontiguousarray(frame[..., :3]))
    draw = ImageDraw.Draw(image)
    box = draw.textbbox((4, 4), text)
    draw.rectangle((box[0] - 2, box[1] - 2, box[2] + 2, box[3] + 2), fill=(0, 0, 0))
    draw.text((4, 4), text, fill=(255, 255, 255))
    return np.asarray(image)


def _world(config: Any) -> tuple[str, Any]:
    """``(env_id, world config)`` of an ``ExperimentConfig`` or of a world config."""
    env_id, world = getattr(config, "env_id", None), getattr(config, "env", None)
    if isinstance(env_id, str) and world is not None:
        return env_id, world
    env_id = getattr(config, "ENV_ID", "")
    if not env_id:
        raise ValueError(
            f"config of type {type(config).__name__}: expected an ExperimentConfig or a "
            "registered world's config (e.g. a SineTrackConfig) that names its env (ENV_ID)"
        )
    return env_id, config


def make_render_env(config: Any, render_mode: str = "rgb_array", **options: Any):
    """``gym.make(env_id, config=world, render_mode=...)`` of an ``ExperimentConfig``'s or a world
    config's world; ``options`` (``screen_size`` [px], ``scaling`` [px/m]) the env does not take
    are left out.
    """
    import gymnasium as gym

    import lfm_env  # noqa: F401  (registers the envs)
    from lfm_env.worlds.registry import import_world_module, split_env_id

    env_id, world = _world(config)
    module, name = split_env_id(env_id)
    if module:  # module:EnvId: the module registers the env (as gym.make imports it)
        import_world_module(module, name)
    entry = gym.spec(name).entry_point
    if not callable(entry):
        from gymnasium.envs.registration import load_env_creator

        entry = load_env_creator(entry)
    params = inspect.signature(entry).parameters
    if not any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values()):
        options = {k: v for k, v in options.items() if k in params}
    return gym.make(env_id, config=world, render_mode=render_mode, **options)


def world_draws(config: Any) -> bool:
    """Whether the config's world has a scene to draw (its env overrides ``_make_scene`` or
    takes a scene factory): a world of one's own may have none, and then a replay shows
    the plan's panel alone."""
    import gymnasium as gym

    import lfm_env  # noqa: F401  (registers the envs)

    env_id, world = _world(config)
    env = gym.make(env_id, config=world)
    try:
        return bool(env.unwrapped.metadata.get("render_modes"))
    finally:
        env.close()


def replay_frames(
    true_state: np.ndarray,
    config: Any,
    screen_size: tuple[int, int] = (480, 240),
    scaling: float | None = None,
    caption: str = "",
) -> list[np.ndarray]:
    """``T+1`` RGB frames ``(height, width, 3)`` uint8: a saved episode in the world's scene.

    Args:
        true_state: ``(T+1, nx)`` true states in the states' units.
        config: an ``ExperimentConfig`` or the world config of the run.
        screen_size: frame ``(width, height)`` [px], if the world's env takes it.
        scaling: [px/m], if the world's env takes it; ``None`` for the world's default.
        caption: text put before the time stamp on each frame.
    """
    options = {} if scaling is None else {"scaling": scaling}
    env = make_render_env(config, screen_size=screen_size, **options)
    try:
        dt = env.unwrapped.model.dt
        scene = env.unwrapped.make_scene()
        frames = []
        try:
            for k, state in enumerate(np.asarray(true_state, dtype=float)):
                scene.update(state)
                frame = scene.draw()
                text = f"t = {k * dt:.1f} s"
                text = f"{caption} | {text}" if caption else text
                frames.append(annotate_frame(frame, text))
        finally:
            scene.close()
    finally:
        env.close()
    return frames


def stack_frames(top: Sequence[np.ndarray], bottom: Sequence[np.ndarray]) -> list[np.ndarray]:
    """Frames of ``top`` over ``bottom``, pairwise (the shorter list sets the count); a
    narrower frame is padded on the right with white to the wider one's width."""
    out = []
    for a, b in zip(top, bottom, strict=False):
        a, b = np.asarray(a)[..., :3], np.asarray(b)[..., :3]
        width = max(a.shape[1], b.shape[1])
        pad = [np.pad(f, ((0, 0), (0, width - f.shape[1]), (0, 0)), constant_values=255)
               for f in (a, b)]  # fmt: skip
        out.append(np.concatenate(pad, axis=0).astype(np.uint8))
    return out


def write_gif(frames: Sequence[np.ndarray], path: str | Path, fps: float) -> Path:
    """Write RGB ``frames`` as a looping GIF at ``fps`` frames per second."""
    import imageio.v3 as iio

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not frames:
        raise ValueError(f"no frames to write to {path}")
    iio.imwrite(path, np.stack(frames), extension=".gif", duration=1000.0 / fps, loop=0)
    return path
