"""One episode and the inputs every run checks first (``experiments.evaluation.episode``):
seeds, the agent's seed, the recorder and its metrics, ``run_episode``."""

from __future__ import annotations

import math
import types

import gymnasium as gym
import numpy as np
import pytest

from experiments.evaluation import episode
from experiments.evaluation.run import (
    agent_seed,
    evaluate,
    parse_seeds,
    row_columns,
    run_episode,
)
from lfm_env import gp
from lfm_env.cost import QuadraticCost
from lfm_env.env import LatentForceEnv
from lfm_env.model import LatentForceModel
from tests.experiments.evaluation.tiny_runs import (
    SINE_TRACK_COLUMNS,
    TINY,
    assert_same_trajectory,
    comparable,
    corridor_system,
)


@pytest.mark.parametrize(
    "text, seeds",
    [
        ("0:20", list(range(20))),
        ("3", [3]),
        ("1,5,9", [1, 5, 9]),
        ("0:10,20:25", [*range(10), *range(20, 25)]),
        (" 2 : 4 , 7 ", [2, 3, 7]),
        ("1,1,0:2", [1, 0]),
    ],
)
def test_parse_seeds(text, seeds):
    assert parse_seeds(text) == seeds


@pytest.mark.parametrize("text", ["5:2", "3:3", "-1", "0:-3", "a", "", "1,,2", "1.5", "0:5:1"])
def test_parse_seeds_rejects_bad_text_naming_it(text):
    with pytest.raises(ValueError) as exc:
        parse_seeds(text)
    assert repr(text) in str(exc.value)


def test_agent_seed_is_stable_and_distinct():
    # A fixed value: the derivation must not depend on the process (hash randomisation).
    assert agent_seed(0, "pf") == 11201204833369463469
    seeds = {agent_seed(s, a) for s in range(3) for a in ("nominal", "pf", "scenario", "oracle")}
    assert len(seeds) == 12


def test_recorder_and_metrics_of_any_system_come_from_its_groups():
    """An episode of a system the evaluation knows nothing about, driven through the
    generic env: the group columns are its own and agree with the env's info."""
    system = corridor_system()
    model = LatentForceModel(system, gp.matern(1.5, 0.5, 1.0), dt=0.1, process_noise_std=[0, 0])
    env = LatentForceEnv(
        model, QuadraticCost(Q=[1, 0], R=[1]), [0.0, 0.5], [0.01, 0.01], max_steps=12
    )
    env = gym.wrappers.TimeLimit(env, env.max_steps)  # a built env never truncates itself
    config = types.SimpleNamespace(
        make_system=lambda: system, agents=types.SimpleNamespace(horizon=3)
    )
    rec = episode._EpisodeRecorder(config)
    obs, info = env.reset(seed=0)
    rec.start(obs, info)
    infos, done = [], False
    while not done:  # push up at full throttle: through the ceiling, beyond the speed bound
        agent_info = {"estimate": obs, "estimate_std": np.zeros(2), "success": True}
        obs, reward, terminated, truncated, info = env.step([1.0])
        rec.step(agent_info, obs, reward, info)
        infos.append(info)
        done = terminated or truncated
    arrays = rec.arrays()
    row = episode._episode_metrics(rec, arrays)
    assert list(row)[4:10] == list(row_columns(system))[6:12]
    corridor = np.array([i["corridor_excess"] for i in infos])
    speed = np.array([i["speed_excess"] for i in infos])
    np.testing.assert_array_equal(arrays["corridor_excess"], corridor)
    np.testing.assert_array_equal(arrays["speed_excess"], speed)
    assert 0 < row["corridor_violation_steps"] == np.sum(corridor > 0) < len(infos)
    # The tolerance-aware counts drop the crossings up to each tolerance, here some.
    over = row["corridor_violation_steps_over_0.1"]
    assert over == np.sum(corridor > 0.1) < row["corridor_violation_steps"]
    assert row["corridor_violation_steps_over_0.01"] == np.sum(corridor > 0.01) >= over
    assert 0 < row["speed_violation_steps"] == np.sum(speed > 0) < len(infos)
    assert row["max_corridor_excess"] == corridor.max() > 0.0
    assert row["max_speed_excess"] == speed.max()
    assert "track_excess" not in arrays and math.isnan(row["latent_rmse"])
    # A failed episode of this system gets the same columns, with NaN metrics.
    failed = episode._error_row("nominal", 0, "boom", 1.0, row_columns(system))
    assert tuple(failed) == row_columns(system) and math.isnan(failed["max_corridor_excess"])


def test_run_episode_row_trajectory_and_time_alignment():
    row, traj = run_episode("pf", TINY, seed=3)
    assert tuple(row) == SINE_TRACK_COLUMNS
    assert row["agent"] == "pf" and row["seed"] == 3 and row["error"] == ""
    assert isinstance(row["success"], bool) and isinstance(row["failure"], bool)
    for c in ("steps", "track_violation_steps", "x_violation_steps", "speed_violation_steps"):
        assert isinstance(row[c], int)
    for c in ("cost", "max_track_excess", "latent_rmse", "latent_coverage", "wall_time"):
        assert isinstance(row[c], float)

    T = row["steps"]
    assert 1 <= T <= TINY["env"]["max_steps"]
    shapes = {
        "true_state": (T + 1, 4),
        "obs": (T + 1, 4),
        "action": (T, 2),
        "latent_force": (T,),
        "estimate": (T, 7),
        "estimate_std": (T, 7),
        "latent_force_est": (T,),
        "latent_force_std": (T,),
        "predicted": (T, TINY["agents"]["horizon"] + 1, 4),
        "solve_time": (T,),
        "slack": (T,),
        "solver_success": (T,),
        "reward": (T,),
    }
    for k, shape in shapes.items():
        assert traj[k].shape == shape, k
    assert traj["solver_success"].dtype == bool

    # The row's metrics are those of the trajectory.
    assert row["cost"] == pytest.approx(-traj["reward"].sum())
    err = traj["latent_force_est"] - traj["latent_force"]
    assert row["latent_rmse"] == pytest.approx(np.sqrt(np.mean(err**2)))
    assert row["slack_total"] == pytest.approx(traj["slack"].sum())
    for g in ("track", "x", "speed"):
        assert traj[f"{g}_excess"].shape == (T,)
        assert row[f"{g}_violation_steps"] == np.sum(traj[f"{g}_excess"] > 0)
        assert row[f"max_{g}_excess"] == traj[f"{g}_excess"].max()

    # Alignment with the env: obs[0] measures true_state[0], and latent_force[0] is the
    # force that the env announces at reset as acting in the first step.
    env = gym.make("lfm_env/SineTrack-v0", config=TINY)
    obs0, info0 = env.reset(seed=3)
    np.testing.assert_array_equal(traj["obs"][0], obs0)
    np.testing.assert_array_equal(traj["true_state"][0], info0["true_state"])
    assert traj["latent_force"][0] == info0["latent_force"]
    # ...and the first action was computed from obs[0] alone: replaying it reproduces step 1.
    _, _, _, _, info1 = env.step(traj["action"][0])
    np.testing.assert_array_equal(traj["true_state"][1], info1["true_state"])
    env.close()


def test_the_plan_and_the_hidden_latent_state_are_recorded_aligned():
    """``plan[k]`` is what the agent planned at step k (its first input applied when no
    fallback), ``latent_state[k]`` the env's hidden latent state acting in step k."""
    row, traj = run_episode("scenario", TINY, seed=2)
    T, N = row["steps"], TINY["agents"]["horizon"]
    env = gym.make("lfm_env/SineTrack-v0", config=TINY)
    _, info = env.reset(seed=2)
    model = env.unwrapped.model
    assert traj["plan"].shape == (T, N, 2)
    assert traj["latent_state"].shape == (T + 1, model.latent_dim)
    planned = traj["fallback"] == ""
    assert planned.any()
    np.testing.assert_array_equal(traj["action"][planned], traj["plan"][planned, 0])
    np.testing.assert_array_equal(traj["latent_state"][0], info["latent_state"])
    forces = model.latent_force(traj["latent_state"][:T])[:, 0]
    np.testing.assert_array_equal(forces, traj["latent_force"])
    env.close()
    # An agent without a plan (the protocol's minimum) records NaN.
    _, bare = run_episode(lambda config: _Coast(), TINY, seed=2)
    assert bare["plan"].shape == (len(bare["action"]), N, 2)
    assert np.all(np.isnan(bare["plan"]))


class _Coast:
    name = "coast"

    def reset(self, seed=None):
        pass

    def act(self, obs):
        return np.zeros(2)


def test_paired_design_and_determinism():
    nominal, traj_n = run_episode("nominal", TINY, seed=5)
    pf, traj_pf = run_episode("pf", TINY, seed=5)
    # Same env seed: the hidden force does not depend on the agent.
    n = min(nominal["steps"], pf["steps"])
    np.testing.assert_array_equal(traj_n["latent_force"][:n], traj_pf["latent_force"][:n])
    np.testing.assert_array_equal(traj_n["obs"][0], traj_pf["obs"][0])
    # Filter metrics exist only for filter agents.
    assert math.isnan(nominal["latent_rmse"]) and math.isnan(nominal["latent_coverage"])
    assert np.isnan(traj_n["latent_force_est"]).all()
    assert set(traj_n["estimator"]) == {""}  # no estimator to name
    assert 0.0 <= pf["latent_coverage"] <= 1.0

    again, traj_again = run_episode("pf", TINY, seed=5)
    assert comparable([again]) == comparable([pf])
    assert_same_trajectory(traj_again, traj_pf)

    _, traj_other = run_episode("nominal", TINY, seed=6)
    assert traj_other["latent_force"][0] != traj_n["latent_force"][0]


def test_run_episode_rejects_unknown_agent_and_negative_seed():
    with pytest.raises(ValueError, match="unknown agent"):
        run_episode("random", TINY, 0)
    with pytest.raises(ValueError, match="-1"):
        run_episode("nominal", TINY, -1)


class _BadInfoAgent:
    """Steers nowhere, with one bad value in its last_info."""

    def __init__(self, key: str, value) -> None:
        self.key, self.value = key, value
        self.last_info: dict = {}

    def reset(self, seed=None) -> None:
        self.last_info = {}

    def act(self, obs):
        self.last_info = {self.key: self.value}
        return np.zeros(2)


@pytest.mark.parametrize(
    "key, value",
    [
        ("solve_time", "fast"),
        ("slack", [1.0, 2.0]),
        ("estimate", [[1.0, 2.0], [3.0, 4.0]]),
        ("estimate_std", "wide"),
        ("latent_force", [1.0, 2.0, 3.0]),
        ("latent_force_std", object()),
        ("predicted", 5.0),
    ],
)
def test_a_bad_last_info_value_is_named_by_its_key(key, value) -> None:
    """Lesser case: a bad last_info value gave an error that did not name its key."""
    agent = _BadInfoAgent(key, value)
    with pytest.raises(ValueError, match=rf"last_info\['{key}'\] of the agent is "):
        episode.run_episode(agent, TINY, 0)
    (row,) = evaluate([agent], [0], TINY, progress=False)
    assert f"last_info['{key}']" in row["error"]
