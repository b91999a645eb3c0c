"""Tests of the SineTrack Gymnasium environment (``lfm_env.env``), through ``gym.make``."""

from __future__ import annotations

import math
import pickle
import subprocess
import sys
import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import lfm_env  # noqa: F401  (registers lfm_env/SineTrack-v0)
from lfm_env.config import EnvConfig
from lfm_env.gp import matern

ENV_ID = "lfm_env/SineTrack-v0"
ALLOWED_WARNING = "For Box action spaces, we recommend using a symmetric and normalized space"
GOAL = np.array([62.83, 0.0])


def make(**kwargs) -> gym.Env:
    return gym.make(ENV_ID, **kwargs)


def action_sequence(n: int, seed: int = 123) -> np.ndarray:
    """A fixed sequence of in-bound actions ``(n, 2)``."""
    rng = np.random.default_rng(seed)
    return rng.uniform([-5.0, -0.4], [5.0, 0.4], size=(n, 2))


def assert_infos_equal(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for key in a:
        np.testing.assert_array_equal(np.asarray(a[key]), np.asarray(b[key]), err_msg=key)


def rollout(env: gym.Env, seed: int, actions: np.ndarray, preview: bool = False) -> list:
    """``[(obs, info), (obs, reward, terminated, truncated, info), ...]`` of one episode."""
    out = [env.reset(seed=seed)]
    for u in actions:
        if preview:
            env.unwrapped.preview_disturbance(200)
        step = env.step(u)
        out.append(step)
        if step[2] or step[3]:
            break
    return out


def assert_rollouts_equal(r1: list, r2: list) -> None:
    assert len(r1) == len(r2)
    for s1, s2 in zip(r1, r2, strict=True):
        np.testing.assert_array_equal(s1[0], s2[0])
        assert s1[1:-1] == s2[1:-1]  # reward, terminated, truncated (empty at reset)
        assert_infos_equal(s1[-1], s2[-1])


# ----------------------------------------------------------------------------- Gymnasium contract


def test_check_env_has_only_the_action_space_recommendation():
    env = make()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env.unwrapped)
    messages = [str(w.message) for w in caught]
    unexpected = [m for m in messages if ALLOWED_WARNING not in m]
    assert unexpected == []
    env.close()


def test_spaces_are_in_physical_units():
    env = make()
    space = env.action_space
    assert space.dtype == np.float64 and space.shape == (2,)
    np.testing.assert_allclose(space.high, [5.0, math.radians(25.0)])
    np.testing.assert_allclose(space.low, [-5.0, -math.radians(25.0)])
    assert env.observation_space.dtype == np.float64 and env.observation_space.shape == (4,)


def test_gym_make_in_a_subprocess():
    code = "import gymnasium as gym, lfm_env; e = gym.make('lfm_env/SineTrack-v0'); e.reset(seed=0)"
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr


def test_observations_are_float64_and_in_the_space():
    env = make()
    obs, _ = env.reset(seed=5)
    observations = [obs]
    for u in action_sequence(40, seed=5):
        obs, _, terminated, truncated, _ = env.step(u)
        observations.append(obs)
        if terminated or truncated:
            break
    for obs in observations:
        assert obs.dtype == np.float64 and obs.shape == (4,)
        assert env.observation_space.contains(obs)


def test_step_before_reset_raises():
    env = make().unwrapped
    with pytest.raises(gym.error.ResetNeeded):
        env.step(np.zeros(2))


# ----------------------------------------------------------------------------- determinism


def test_two_envs_same_seed_same_episode_bit_for_bit():
    actions = action_sequence(60)
    r1 = rollout(make(), 7, actions)
    r2 = rollout(make(), 7, actions)
    assert len(r1) > 10
    assert_rollouts_equal(r1, r2)


def test_reset_with_the_same_seed_repeats_the_episode():
    env = make()
    actions = action_sequence(30)
    assert_rollouts_equal(rollout(env, 11, actions), rollout(env, 11, actions))


def test_same_seed_same_disturbance_other_seed_other_disturbance():
    env1, env2 = make(), make()
    env1.reset(seed=3)
    env2.reset(seed=3)
    w1 = env1.unwrapped.preview_disturbance(100)
    np.testing.assert_array_equal(w1, env2.unwrapped.preview_disturbance(100))
    env2.reset(seed=4)
    w2 = env2.unwrapped.preview_disturbance(100)
    assert not np.any(w1 == w2)
    # The hidden force is redrawn at every reset, also without a new seed.
    env1.reset()
    assert not np.any(env1.unwrapped.preview_disturbance(100) == w1)


def test_pickle_round_trip_of_a_reset_env():
    env = make()
    env.reset(seed=9)
    env.step([1.0, 0.1])
    clone = pickle.loads(pickle.dumps(env))
    for u in action_sequence(20, seed=9):
        s1, s2 = env.step(u), clone.step(u)
        np.testing.assert_array_equal(s1[0], s2[0])
        assert s1[1:4] == s2[1:4]
        assert_infos_equal(s1[4], s2[4])


def test_reset_options_take_effect():
    env = make()
    x0 = np.array([5.0, 3.0 * math.sin(1.0) + 0.2, 2.0, -0.3])
    z0 = np.array([1.5, -0.2, 0.05])
    _, info = env.reset(seed=0, options={"initial_state": x0, "latent_state": z0})
    np.testing.assert_array_equal(info["true_state"], x0)
    np.testing.assert_array_equal(info["latent_state"], z0)
    assert info["disturbance"] == 1.5  # w = H z, H = [1, 0, 0]
    np.testing.assert_array_equal(env.unwrapped.true_state, x0)
    _, _, _, _, info = env.step([0.0, 0.0])
    assert info["disturbance"] == 1.5  # the force that acted during the first step
    # The speed moves by (a + w) dt plus a small process noise (std 0.0045 m/s).
    assert info["true_state"][2] == pytest.approx(2.0 + 1.5 * 0.2, abs=0.03)
    # Without options the paper's start state is back.
    _, info = env.reset(seed=0)
    np.testing.assert_allclose(info["true_state"], [0.0, 0.0, 1.0, math.pi / 4])


@pytest.mark.parametrize(
    "options, match",
    [
        ({"initial_sate": [0.0, 0.0, 1.0, 0.0]}, "unknown reset option"),
        ({"initial_state": [0.0, 0.0, 1.0]}, "initial_state"),
        ({"latent_state": [0.0, math.nan, 0.0]}, "latent_state"),
    ],
)
def test_bad_reset_options_raise(options, match):
    env = make()
    with pytest.raises(ValueError, match=match):
        env.reset(seed=0, options=options)


# ----------------------------------------------------------------------------- disturbance


def test_preview_does_not_change_the_episode_and_foretells_the_disturbance():
    # A huge safety box so the episode lasts long enough to cross the 64-step chunks.
    config = {"env": {"safety_margin": 1.0e6}}
    actions = np.zeros((140, 2))
    plain = rollout(make(config=config), 21, actions)
    previewed = rollout(make(config=config), 21, actions, preview=True)
    assert len(plain) == 141
    assert_rollouts_equal(plain, previewed)

    env = make(config=config)
    _, info = env.reset(seed=21)
    preview = env.unwrapped.preview_disturbance(140)
    assert preview.shape == (140,)
    assert preview[0] == info["disturbance"]
    seen = [env.step(u)[4]["disturbance"] for u in actions]
    np.testing.assert_array_equal(preview, seen)
    np.testing.assert_array_equal(preview, [s[-1]["disturbance"] for s in plain[1:]])
    assert env.unwrapped.preview_disturbance(0).shape == (0,)


def test_disturbance_statistics_match_the_matern_kernel():
    """Over 500 resets the force has the kernel's variance and lag-1 s correlation."""
    n, lag = 500, 5  # lag 5 steps = 1 s at dt = 0.2 s
    env = make()
    w = np.empty((n, lag + 1))
    for seed in range(n):
        _, info = env.reset(seed=seed)
        w[seed] = env.unwrapped.preview_disturbance(lag + 1)
        assert w[seed, 0] == info["disturbance"]
    kernel = matern(2.5, 4.0, 4.0)
    k0, k1 = kernel.covariance([0.0, 1.0])
    rho = k1 / k0

    # Mean: SE = sigma / sqrt(n).
    assert abs(w[:, 0].mean()) < 4.5 * math.sqrt(k0 / n)
    # Variance of n independent Gaussian draws: SE = sigma^2 sqrt(2 / (n - 1)).
    se_var = k0 * math.sqrt(2.0 / (n - 1))
    for col in (0, lag):
        assert w[:, col].var(ddof=1) == pytest.approx(k0, abs=4.5 * se_var)
    # Correlation at lag 1 s: Fisher's z = atanh(r) has SE 1 / sqrt(n - 3).
    r = np.corrcoef(w[:, 0], w[:, lag])[0, 1]
    assert abs(math.atanh(r) - math.atanh(rho)) < 4.5 / math.sqrt(n - 3)


def test_euler_maruyama_zero_start_begins_at_zero():
    config = {"env": {"disturbance": {"discretization": "euler_maruyama", "start": "zero"}}}
    env = make(config=config)
    _, info = env.reset(seed=0)
    assert info["disturbance"] == 0.0
    np.testing.assert_array_equal(info["latent_state"], np.zeros(3))
    _, _, _, _, info = env.step([0.0, 0.0])
    assert info["disturbance"] == 0.0
    # Afterwards the force moves (rank-1 noise enters through the third latent state).
    assert np.any(env.unwrapped.preview_disturbance(10) != 0.0)


# ----------------------------------------------------------------------------- episode end


def reset_at(env: gym.Env, state, latent=(0.0, 0.0, 0.0), seed: int = 0):
    return env.reset(seed=seed, options={"initial_state": state, "latent_state": latent})


def test_goal_reached_without_tunnelling():
    env = make()
    # 20 m/s for 0.2 s: the car jumps from 2.83 m before the goal to 1.17 m after it.
    _, info = reset_at(env, [60.0, 0.0, 20.0, 0.0])
    assert np.linalg.norm(info["true_state"][:2] - GOAL) > 1.0
    _, _, terminated, truncated, info = env.step([0.0, 0.0])
    assert np.linalg.norm(info["true_state"][:2] - GOAL) > 1.0  # both ends outside the disc
    assert terminated and not truncated
    assert info["is_success"] and not info["failure"]


@pytest.mark.parametrize("offset, success", [(1.5, False), (-1.2, False), (0.9, True)])
def test_passing_beside_the_goal(offset, success):
    env = make()
    reset_at(env, [60.0, offset, 20.0, 0.0])
    _, _, terminated, truncated, info = env.step([0.0, 0.0])
    assert info["is_success"] is success
    assert terminated is success
    assert not truncated and not info["failure"]


def test_leaving_the_safety_box_is_a_failure():
    env = make()
    track = EnvConfig().track
    y_far = float(track.centre_y(10.0)) + 1.0 + 9.5  # 9.5 m outside the band: inside the box
    _, info = reset_at(env, [10.0, y_far, 0.0, 0.0])
    assert info["track_excess"] == pytest.approx(9.5)
    _, _, terminated, _, info = env.step([0.0, 0.0])
    assert not terminated and not info["failure"]
    reset_at(env, [10.0, y_far, 5.0, math.pi / 2])  # 1 m further out in one step
    _, _, terminated, truncated, info = env.step([0.0, 0.0])
    assert terminated and not truncated
    assert info["failure"] and not info["is_success"]
    assert info["track_excess"] > 10.0
    # Beyond the x bounds too.
    reset_at(env, [79.5, float(track.centre_y(79.5)), 5.0, 0.0])
    _, _, terminated, _, info = env.step([0.0, 0.0])
    assert terminated and info["failure"] and info["x_excess"] > 10.0


def test_truncation_after_max_steps():
    env = make(config={"env": {"max_steps": 3}})
    env.reset(seed=0)
    flags = [env.step([0.0, 0.0])[2:4] for _ in range(3)]
    assert flags == [(False, False), (False, False), (False, True)]


def test_constraint_excesses_are_recorded():
    env = make()
    _, info = reset_at(env, [20.0, float(EnvConfig().track.centre_y(20.0)) + 1.4, 9.0, 0.0])
    assert info["track_excess"] == pytest.approx(0.4)
    assert info["speed_excess"] == pytest.approx(1.0)
    assert info["x_excess"] == 0.0


# ----------------------------------------------------------------------------- actions and reward


@pytest.mark.parametrize(
    "action, match",
    [
        ([math.nan, 0.0], "finite"),
        ([0.0, math.inf], "finite"),
        ([1.0], "shape"),
        ([[1.0, 0.0]], "shape"),
        (np.zeros(3), "shape"),
        ("abc", "action"),
        (["a", "b"], "action"),
    ],
)
def test_invalid_actions_raise(action, match):
    env = make()
    env.reset(seed=0)
    with pytest.raises(ValueError, match=match):
        env.step(action)


def test_out_of_range_actions_are_clipped():
    env, ref = make(), make()
    env.reset(seed=2)
    ref.reset(seed=2)
    clipped = np.array([5.0, -math.radians(25.0)])
    s1 = env.step([100.0, -2.0])
    s2 = ref.step(clipped)
    np.testing.assert_allclose(s1[4]["applied_action"], clipped, rtol=1e-15)
    np.testing.assert_array_equal(s1[0], s2[0])
    assert s1[1] == s2[1]
    in_range = np.array([1.0, 0.1])
    np.testing.assert_array_equal(env.step(in_range)[4]["applied_action"], in_range)


def test_reward_is_minus_the_stage_cost():
    env = make()
    _, info = env.reset(seed=4)
    q = np.array([2.0, 2.0, 1.0, 0.0])
    r = np.array([0.5, 10.0])
    x_goal = np.array([62.83, 0.0, 4.0, 0.0])
    actions = np.vstack([action_sequence(10, seed=4), [[9.0, 1.0]]])  # last one is clipped
    for u in actions:
        x = info["true_state"]
        _, reward, _, _, info = env.step(u)
        applied = np.clip(u, [-5.0, -math.radians(25.0)], [5.0, math.radians(25.0)])
        cost = sum(q[i] * (x[i] - x_goal[i]) ** 2 for i in range(4))
        cost += sum(r[j] * applied[j] ** 2 for j in range(2))
        assert reward == pytest.approx(-cost, rel=1e-12)


# ----------------------------------------------------------------------------- noise


def test_measurement_noise_std_over_many_resets():
    n = 1000
    env = make()
    noise = np.empty((n, 4))
    for seed in range(n):
        obs, info = env.reset(seed=seed)
        noise[seed] = obs - info["true_state"]
    std = np.array([0.15, 0.15, 0.15, math.radians(0.5)])
    # SE of a sample std of Gaussian data: sigma / sqrt(2 (n - 1)).
    np.testing.assert_allclose(
        noise.std(axis=0, ddof=1), std, atol=0, rtol=4.5 / math.sqrt(2 * (n - 1))
    )
    assert np.all(np.abs(noise.mean(axis=0)) < 4.5 * std / math.sqrt(n))


# ----------------------------------------------------------------------------- rendering


def white_pixels(frame: np.ndarray) -> np.ndarray:
    return np.all(frame >= 250, axis=-1)


def yellowish_pixels(frame: np.ndarray) -> np.ndarray:
    r, g, b = (frame[..., i].astype(int) for i in range(3))
    return (r > 150) & (g > 150) & (b < 100)


def assert_road_and_car_near_centre(frame: np.ndarray, size=(300, 600)) -> None:
    assert frame.shape == (*size, 3) and frame.dtype == np.uint8
    assert len(np.unique(frame.reshape(-1, 3), axis=0)) > 2  # not blank or uniform
    assert white_pixels(frame).sum() > 100  # lane lines
    h, w = size
    centre = yellowish_pixels(frame)[h // 2 - 40 : h // 2 + 40, w // 2 - 40 : w // 2 + 40]
    assert centre.sum() > 20  # the car, centred because the view follows it


def test_rgb_array_frame_shows_road_and_car():
    env = make(render_mode="rgb_array")
    env.reset(seed=0)
    assert_road_and_car_near_centre(env.render())
    for _ in range(5):
        env.step([2.0, 0.0])
    assert_road_and_car_near_centre(env.render())  # still centred after moving
    env.close()


def test_rgb_array_frame_not_blank_under_sdl_dummy(monkeypatch):
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    env = make(render_mode="rgb_array", screen_size=(400, 200))
    env.reset(seed=0)
    assert_road_and_car_near_centre(env.render(), size=(200, 400))
    env.close()


def test_render_whole_track_when_not_following():
    env = make(render_mode="rgb_array", follow=False)
    env.reset(seed=0)
    frame = env.render()
    h, w = frame.shape[:2]
    cols = np.nonzero(white_pixels(frame).any(axis=0))[0]
    assert cols.min() < 0.1 * w and cols.max() > 0.9 * w
    assert len(cols) > 0.8 * w  # lane lines across the whole width
    assert yellowish_pixels(frame)[:, : w // 10].sum() > 0  # the car at the start, on the left
    env.close()


def test_render_without_render_mode_warns_and_returns_none():
    env = make().unwrapped
    env.reset(seed=0)
    with pytest.warns(UserWarning, match="render_mode"):
        assert env.render() is None
