"""Regenerate ``sine_track_episodes.npz``: SineTrack episodes recorded bit for bit.

Run from the repository root: ``.venv/bin/python tests/data/make_sine_track_episodes.py``.
The file was recorded with the env as it was before the generic ``LatentForceEnv``
(issue 11), by running this script with ``PYTHONPATH`` pointing at that checkout; the test
``tests/lfm_env/test_env.py::test_episodes_match_the_recording`` asserts that today's env
reproduces every number exactly. Regenerate it only when the dynamics, the reward or the
random streams change on purpose (and bump the env's version then).

Recorded: the paper config for env seeds 0, 1, 2 and the published code's latent force
(Euler-Maruyama, zero start; no failure) for seed 3, each driven by one fixed action sequence of
:data:`N_STEPS` actions (a few out of range, so clipping is covered) until the episode ends;
per step the observation, reward, flags and every ``info`` entry, and at reset a preview of
the hidden force over :data:`N_PREVIEW` steps (it crosses the latent path's chunks).
"""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import numpy as np

import lfm_env  # noqa: F401  (registers lfm_env/SineTrack-v0)

ROOT = Path(__file__).resolve().parents[2]
OUT = Path(__file__).with_name("sine_track_episodes.npz")
PAPER = ROOT / "configs" / "paper.yaml"
#: The published code's force, and a safety box so wide that the episode runs all its steps.
PUBLISHED = {
    "env": {
        "latent_force": {"discretization": "euler_maruyama", "start": "zero"},
        "safety_margin": 1.0e6,
    }
}
#: (name, config, seed) of each recorded episode.
EPISODES = (
    ("paper_seed0", PAPER, 0),
    ("paper_seed1", PAPER, 1),
    ("paper_seed2", PAPER, 2),
    ("published_seed3", PUBLISHED, 3),
)
N_STEPS = 60
N_PREVIEW = 150
#: info entries of the pre-refactor env (the new one may add more).
INFO_KEYS = (
    "true_state",
    "latent_force",
    "latent_state",
    "track_excess",
    "speed_excess",
    "x_excess",
    "is_success",
    "failure",
    "applied_action",
    "time",
)


def actions() -> np.ndarray:
    """The fixed action sequence ``(N_STEPS, 2)`` [m/s^2, rad]: gentle, with some clipped."""
    k = np.arange(N_STEPS)
    u = np.stack([1.0 + 2.0 * np.sin(0.3 * k), 0.25 * np.sin(0.15 * k + 0.5)], axis=1)
    u[[7, 31]] = [[9.0, -1.0], [-7.5, 0.8]]  # outside |a| <= 5, |delta| <= 25 deg
    return u


def record(config, seed: int) -> dict[str, np.ndarray]:
    """One episode as arrays: ``reset_*`` at reset, per-step arrays over the steps taken."""
    env = gym.make("lfm_env/SineTrack-v0", config=config)
    obs, info = env.reset(seed=seed)
    out = {
        "reset_obs": obs,
        "preview": np.reshape(env.unwrapped.preview_latent_force(N_PREVIEW), (N_PREVIEW, -1)),
    }
    out.update({f"reset_{k}": np.asarray(info[k]) for k in INFO_KEYS})
    steps: dict[str, list] = {
        k: [] for k in ("obs", "reward", "terminated", "truncated", *INFO_KEYS)
    }
    for u in actions():
        obs, reward, terminated, truncated, info = env.step(u)
        for key, value in zip(
            ("obs", "reward", "terminated", "truncated"),
            (obs, reward, terminated, truncated),
            strict=True,
        ):
            steps[key].append(value)
        for key in INFO_KEYS:
            steps[key].append(info[key])
        if terminated or truncated:
            break
    out.update({key: np.asarray(values) for key, values in steps.items()})
    env.close()
    return out


def main() -> None:
    data = {"actions": actions()}
    for name, config, seed in EPISODES:
        episode = record(config, seed)
        data.update({f"{name}/{key}": value for key, value in episode.items()})
        print(
            f"{name}: {len(episode['reward'])} steps, "
            f"success={episode['is_success'][-1]}, failure={episode['failure'][-1]}"
        )
    np.savez_compressed(OUT, **data)
    print(f"-> {OUT} (recorded with {Path(lfm_env.__file__).parent})")


if __name__ == "__main__":
    main()
