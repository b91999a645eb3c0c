"""Gymnasium conventions of the registered envs: the time limit is a ``TimeLimit`` wrapper
(the config's length by default, ``max_episode_steps`` when given), a float64 observation
Box with finite bounds that hold, a float32 action Box, ``info["violated_groups"]``,
``RecordVideo``, Gymnasium's and SB3's ``check_env``."""

from __future__ import annotations

import os
import subprocess
import sys
import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.wrappers import RecordVideo, TimeAwareObservation, TimeLimit

import lfm_env  # noqa: F401  (registers the envs)
from lfm_env.wrappers import ConfigTimeLimit, inner_time_limit

ENV_IDS = ("lfm_env/SineTrack-v0", "lfm_env/QuadrotorGust-v1")
# Far from the goal, slow and with a generous safety box: no success, no failure for
# hundreds of steps with the coasting input (the car rolls on at 1 m/s, the quadrotor hovers).
NEVER_ENDS = {
    "lfm_env/SineTrack-v0": {
        "env": {"max_steps": 20, "safety_margin": 1000.0, "latent_force": {"variance": 1e-6}}
    },
    "lfm_env/QuadrotorGust-v1": {
        "env": {"max_steps": 20, "safety_margin": 1000.0, "latent_force": {"variance": 1e-6}}
    },
}


def coast(env: gym.Env) -> np.ndarray:
    """No acceleration and no steering for the car, hovering for the quadrotor."""
    if env.spec.id == ENV_IDS[0]:
        return np.zeros(2)
    return env.unwrapped.system.fallback_input


def run_until_done(env: gym.Env, seed: int = 0) -> tuple[int, bool, bool]:
    """Steps with :func:`coast` until the episode ends: ``(steps, terminated, truncated)``."""
    env.reset(seed=seed)
    rest = coast(env)
    for k in range(1, 10_000):
        _, _, terminated, truncated, _ = env.step(rest)
        if terminated or truncated:
            return k, terminated, truncated
    raise AssertionError("episode did not end")


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_default_truncation_is_the_configs_max_steps(env_id):
    env = gym.make(env_id, config=NEVER_ENDS[env_id])
    assert env.spec.max_episode_steps == 20
    assert run_until_done(env) == (20, False, True)
    # The registered default config: its own max_steps.
    default = gym.make(env_id)
    assert default.spec.max_episode_steps == default.unwrapped.config.max_steps


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_max_episode_steps_of_make_wins_over_the_config(env_id):
    env = gym.make(env_id, config=NEVER_ENDS[env_id], max_episode_steps=300)
    assert env.spec.max_episode_steps == 300
    assert run_until_done(env) == (300, False, True)
    short = gym.make(env_id, config=NEVER_ENDS[env_id], max_episode_steps=5)
    assert short.spec.max_episode_steps == 5
    assert run_until_done(short) == (5, False, True)


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_the_env_itself_never_truncates(env_id):
    env = gym.make(env_id, config=NEVER_ENDS[env_id])
    rest = coast(env)
    env = env.unwrapped
    env.reset(seed=0)
    assert not any(env.step(rest)[3] for _ in range(60))


def test_time_aware_observation_reads_the_limit():
    env = TimeAwareObservation(gym.make(ENV_IDS[0], config=NEVER_ENDS[ENV_IDS[0]]))
    obs, _ = env.reset(seed=0)
    assert obs.shape == (5,) and env.observation_space.high[-1] == 20
    obs, *_ = env.step(np.zeros(2))
    assert obs[-1] == 1


def test_config_time_limit_on_a_bare_env_uses_max_steps():
    env = ConfigTimeLimit(gym.make(ENV_IDS[0], config=NEVER_ENDS[ENV_IDS[0]]).unwrapped)
    assert env.spec is None or env.spec.max_episode_steps == 20
    assert run_until_done(env) == (20, False, True)
    inner = TimeLimit(gym.make(ENV_IDS[0]).unwrapped, 7)
    assert inner_time_limit(ConfigTimeLimit(inner)) is not None
    assert ConfigTimeLimit(inner)._max_episode_steps == 7


def test_config_time_limit_refuses_an_env_without_max_steps():
    from gymnasium.envs.classic_control import CartPoleEnv

    with pytest.raises(ValueError, match=r"max_steps=None: must be an integer >= 1"):
        ConfigTimeLimit(CartPoleEnv())


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_spaces_dtypes_and_observations_inside(env_id):
    env = gym.make(env_id)
    assert env.action_space.dtype == np.float32
    space = env.observation_space
    assert space.dtype == np.float64
    # Finite bounds, float32-representable (a float32 copy of the space is the same box).
    assert np.all(np.isfinite(space.low)) and np.all(np.isfinite(space.high))
    assert np.array_equal(space.low.astype(np.float32), space.low)
    assert np.array_equal(space.high.astype(np.float32), space.high)
    obs, _ = env.reset(seed=1)
    assert obs.dtype == np.float64 and space.contains(obs)
    obs, *_ = env.step(env.action_space.sample())
    assert obs.dtype == np.float64 and space.contains(obs)


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_the_observation_bounds_are_the_safety_box_plus_the_noises_reach(env_id):
    """Issue 35, item 7: the observation space was Box(-inf, inf)."""
    from lfm_env.env import FLOAT32_MAX, NOISE_REACH

    env = gym.make(env_id).unwrapped
    cfg, space = env.config, env.observation_space
    std, m = env.measurement_std, cfg.safety_margin
    x_low = cfg.x_min - 2 * m - NOISE_REACH * std[0]
    assert space.low[0] == pytest.approx(x_low, rel=1e-6) and space.low[0] <= x_low
    assert np.all(space.high[2:] == FLOAT32_MAX) and np.all(space.low[2:] == -FLOAT32_MAX)
    # Every state the safety box keeps is observed inside the box, however unlucky the noise.
    low, high = (b[:2] for b in env.state_bounds())
    assert np.all(high + NOISE_REACH * std[:2] <= space.high[:2])
    assert np.all(low - NOISE_REACH * std[:2] >= space.low[:2])
    # A state beyond the box (only the last of a failed episode) is observed clipped to it.
    state = np.array(env.initial_state)
    state[0] = cfg.x_max + 1000.0
    obs, _ = env.reset(seed=0, options={"initial_state": state})
    assert obs[0] == space.high[0] and space.contains(obs)


def test_numpys_normal_draws_stay_within_the_noise_reach():
    """The reach holds: NumPy's ziggurat draws no float64 normal beyond 13.71 in magnitude."""
    from lfm_env.env import NOISE_REACH

    z = np.random.default_rng(0).standard_normal(2_000_000)
    assert np.max(np.abs(z)) < 6.0 < 13.71 < NOISE_REACH  # the tail is out of a test's reach


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_gymnasiums_check_env_warns_only_about_the_physical_action_units(env_id):
    """Gymnasium's checker on the envs: no warning, but the sine track's recommendation to
    normalise its physical action space ([m/s^2, rad]); RescaleAction is the documented fix
    (SB3's checker below), and then Gymnasium's checker only notes the wrapper."""
    from gymnasium.utils.env_checker import check_env

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(gym.make(env_id).unwrapped, skip_render_check=True)
    messages = [str(w.message) for w in caught]
    if env_id == ENV_IDS[0]:
        assert len(messages) == 1
        assert "recommend using a symmetric and normalized space" in messages[0]
    else:
        assert messages == []
    rescaled = gym.wrappers.RescaleAction(
        gym.make(env_id).unwrapped, np.float32(-1.0), np.float32(1.0)
    )
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(rescaled, skip_render_check=True)
    assert [m for m in map(str, (w.message for w in caught)) if "unwrapped" not in m] == []


def test_check_env_headless_prints_no_sdl_error_and_offers_no_human_mode():
    """Issue 35, item 8: check_env tried the human mode on a headless machine and SDL printed
    "XDG_RUNTIME_DIR is invalid"."""
    code = (
        "import warnings, gymnasium as gym, lfm_env\n"
        "from gymnasium.utils.env_checker import check_env\n"
        "for env_id in ('lfm_env/SineTrack-v0', 'lfm_env/QuadrotorGust-v1'):\n"
        "    env = gym.make(env_id)\n"
        "    assert 'human' not in env.unwrapped.metadata['render_modes']\n"
        "    with warnings.catch_warnings():\n"
        "        warnings.simplefilter('ignore')\n"
        "        check_env(env.unwrapped)  # with the render modes' check\n"
        "try:\n"
        "    gym.make('lfm_env/SineTrack-v0', render_mode='human')\n"
        "except ValueError as exc:\n"
        "    print(exc)\n"
    )
    environ = {k: v for k, v in os.environ.items() if not k.startswith("SDL_")}
    for key in ("XDG_RUNTIME_DIR", "DISPLAY", "WAYLAND_DISPLAY"):
        environ.pop(key, None)
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=environ, timeout=300
    )
    assert done.returncode == 0, done.stderr
    assert "XDG_RUNTIME_DIR" not in done.stderr and "error" not in done.stderr.lower()
    assert "render_mode='human': no display" in done.stdout


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_info_cost_counts_the_violated_constraint_groups(env_id):
    env = gym.make(env_id, config={"env": {"safety_margin": 1000.0}})
    system = env.unwrapped.system
    groups = list(system.constraint_groups)
    seen = set()
    for seed in range(3):
        obs, info = env.reset(seed=seed)
        rng = np.random.default_rng(seed)
        for _ in range(40):
            u = rng.uniform(env.action_space.low, env.action_space.high)
            _, _, terminated, truncated, info = env.step(u)
            violated = sum(info[f"{g}_excess"] > 0.0 for g in groups)
            assert info["violated_groups"] == float(violated) >= 0.0
            assert (info["violated_groups"] > 0.0) == bool(np.any(info["constraint_excess"] > 0.0))
            seen.add(info["violated_groups"] > 0.0)
            if terminated or truncated:
                break
    assert seen == {True, False}  # both cases met


def test_info_cost_at_reset_from_a_violating_state():
    env = gym.make(ENV_IDS[0])
    _, info = env.reset(seed=0, options={"initial_state": [20.0, 9.0, 9.0, 0.0]})
    assert info["violated_groups"] == 2.0  # off the track and too fast; x inside
    _, info = env.reset(seed=0)
    assert info["violated_groups"] == 0.0


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_sb3_check_env_has_at_most_the_action_normalisation_warning(env_id):
    pytest.importorskip("stable_baselines3")
    from stable_baselines3.common.env_checker import check_env

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(gym.make(env_id))
    messages = [str(w.message) for w in caught]
    assert [m for m in messages if "symmetric and normalized Box action space" not in m] == []
    # With the documented wrapper (float32 bounds, so the float32 space is not warned
    # about lost precision), not even that one.
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(gym.wrappers.RescaleAction(gym.make(env_id), np.float32(-1.0), np.float32(1.0)))
    assert [str(w.message) for w in caught] == []


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_record_video_writes_a_file(tmp_path, env_id):
    pytest.importorskip("moviepy")
    env = gym.make(env_id, render_mode="rgb_array", config={"env": {"max_steps": 4}})
    env = RecordVideo(env, str(tmp_path), episode_trigger=lambda _: True, disable_logger=True)
    env.reset(seed=0)
    done = False
    while not done:
        _, _, terminated, truncated, _ = env.step(env.unwrapped.system.fallback_input)
        done = terminated or truncated
    env.close()
    videos = list(tmp_path.glob("*.mp4"))
    assert len(videos) == 1 and videos[0].stat().st_size > 1000


def test_offscreen_rendering_prints_no_sdl_error():
    code = (
        "import gymnasium as gym, lfm_env\n"
        "env = gym.make('lfm_env/SineTrack-v0', render_mode='rgb_array')\n"
        "env.reset(seed=0)\n"
        "frame = env.render()\n"
        "assert frame.shape == (300, 600, 3) and frame.std() > 0\n"
        "env.close()\n"
    )
    environ = {k: v for k, v in os.environ.items() if not k.startswith("SDL_")}
    environ.pop("XDG_RUNTIME_DIR", None)
    environ.pop("DISPLAY", None)
    environ.pop("WAYLAND_DISPLAY", None)
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=environ, timeout=120
    )
    assert done.returncode == 0, done.stderr
    assert "XDG_RUNTIME_DIR" not in done.stderr and "error" not in done.stderr.lower()
