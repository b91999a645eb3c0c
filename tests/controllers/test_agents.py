"""Agents through the standard step API: episodes, determinism, faults, configuration."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import lfm_env  # noqa: F401  (registers the env)
from controllers.agents import AGENT_REGISTRY, make_agent
from controllers.agents.mpc import ScenarioMPCAgent
from controllers.config import AgentConfig, load_config
from controllers.scenario_count import campi_garatti_scenarios
from controllers.solvers import SOLVERS
from lfm_env import gp
from lfm_env.config import ConfigError
from lfm_env.cost import QuadraticCost
from lfm_env.env import LatentForceEnv
from lfm_env.model import LatentForceModel
from lfm_env.system import ControlSystem
from lfm_env.xp import xp

QUICK = "configs/quick.yaml"


# sqpmethod's JIT build takes 15-50 s: its case runs with the slow tests (CI runs them).
SOLVER_CASES = [pytest.param(s, marks=pytest.mark.slow) if s == "sqpmethod" else s for s in SOLVERS]


def run(agent_name: str, config, seed: int = 0, max_steps: int | None = None):
    env = gym.make("lfm_env/SineTrack-v0", config=config)
    agent = make_agent(agent_name, config, env=env if agent_name == "oracle" else None)
    obs, info = env.reset(seed=seed)
    agent.reset(seed=100 + seed)
    actions, infos, est = [], [info], []
    for _ in range(max_steps or 10_000):
        a = agent.act(obs)
        actions.append(a)
        est.append(agent.last_info)
        obs, _, term, trunc, info = env.step(a)
        infos.append(info)
        if term or trunc:
            break
    return np.array(actions), infos, est


@pytest.mark.parametrize("name", sorted(set(AGENT_REGISTRY) - {"rl"}))  # rl: test_rl_agent.py
def test_each_agent_reaches_the_goal_on_the_quick_config(name):
    actions, infos, est = run(name, QUICK, seed=0)
    assert infos[-1]["is_success"], f"{name} did not reach the goal"
    assert not infos[-1]["failure"]
    # Inputs respect the bounds exactly.
    assert np.all(np.abs(actions[:, 0]) <= 5.0 + 1e-12)
    assert np.all(np.abs(actions[:, 1]) <= np.deg2rad(25.0) + 1e-12)
    for rec in est:
        assert rec["solve_time"] >= 0.0
        assert {"status", "iterations", "slack", "estimate", "estimate_std"} <= set(rec)


def test_filter_agents_track_the_hidden_force():
    cfg = {"env": {"max_steps": 40}, "agents": {"n_particles": 3000, "n_scenarios": 5}}
    _, infos, est = run("pf", cfg, seed=3)
    w_true = np.array([i["latent_force"] for i in infos[1:]])
    w_hat = np.array([r["latent_force"] for r in est])[:, 0]  # (T, nw) with nw = 1
    # Skip the first second while the filter learns; the force's std is 2 m/s^2.
    err = w_hat[5:] - w_true[5:]
    assert np.sqrt(np.mean(err**2)) < 1.2
    band = np.array([r["latent_force_std"] for r in est])[5:, 0]
    assert np.mean(np.abs(err) <= 2 * band + 1e-9) > 0.6


def test_same_seeds_give_identical_actions():
    a1, _, _ = run("scenario", QUICK, seed=1, max_steps=8)
    a2, _, _ = run("scenario", QUICK, seed=1, max_steps=8)
    np.testing.assert_array_equal(a1, a2)


def test_agent_seed_does_not_change_the_latent_force():
    env_a = gym.make("lfm_env/SineTrack-v0", config=QUICK)
    env_b = gym.make("lfm_env/SineTrack-v0", config=QUICK)
    _, ia = env_a.reset(seed=5)
    _, ib = env_b.reset(seed=5)
    assert ia["latent_force"] == ib["latent_force"]


def test_solver_failure_falls_back_to_the_previous_plan_then_to_the_systems_fallback():
    # No time for one IPOPT iteration: no solve has a usable plan, a real fault.
    agents = {"max_solve_time": 1e-9, "solver": "ipopt", "n_scenarios": 3, "n_particles": 200}
    agent = make_agent("nominal", {"agents": agents})
    agent.reset(seed=0)
    obs = np.array([0.0, 0.0, 1.0, np.pi / 4])
    u = agent.act(obs)
    assert not agent.last_info["success"] and not agent.last_info["usable"]
    assert agent.last_info["fallback"] == "fallback"
    np.testing.assert_allclose(u, [-5.0, 0.0])  # the bicycle's fallback: full braking


def test_previous_plan_is_used_after_a_good_solve():
    good = make_agent("nominal", {"agents": {"solver": "ipopt"}})
    good.reset(seed=0)
    obs = np.array([0.0, 0.0, 1.0, np.pi / 4])
    good.act(obs)
    plan = good.last_info["plan"]
    # Now make the same solver fail by starving it of time.
    bad = make_agent("nominal", {"agents": {"solver": "ipopt", "max_solve_time": 1e-9}})
    bad.reset(seed=0)
    bad._plan = plan.copy()  # as if the previous step had solved
    u = bad.act(obs + 0.1)
    assert bad.last_info["fallback"] == "previous_plan"
    np.testing.assert_allclose(u, plan[1])


@pytest.mark.parametrize(
    "obs", [[np.nan, 0, 1, 0], [0, 0, np.inf, 0], [0, 0, 1], [[0, 0, 1, 0]]], ids=str
)
def test_bad_observations_are_rejected(obs):
    agent = make_agent("nominal", QUICK)
    agent.reset(seed=0)
    with pytest.raises(ValueError, match="obs"):
        agent.act(obs)


def test_factory_errors():
    with pytest.raises(ValueError, match="unknown agent 'mpc'"):
        make_agent("mpc")
    with pytest.raises(ValueError, match="oracle"):
        make_agent("oracle", QUICK)
    env = gym.make("lfm_env/SineTrack-v0")
    with pytest.raises(ValueError, match="only the oracle"):
        make_agent("scenario", QUICK, env=env)


@pytest.mark.parametrize(
    "section, key",
    [
        ({"horizon": 0}, "horizon"),
        ({"n_scenarios": 0}, "n_scenarios"),
        ({"n_particles": -5}, "n_particles"),
        ({"solver": "cplex"}, "solver"),
        ({"resampling": "magic"}, "resampling"),
        ({"ess_threshold": 1.5}, "ess_threshold"),
        ({"violation_level": 1.2, "n_scenarios": None, "confidence": 0.1}, "violation_level"),
        ({"n_scenarios": None}, "n_scenarios"),
        ({"Q": [1, 1, 1]}, "agents.Q"),
        ({"goal_state": [1, 1, 1, 1, 1]}, "agents.goal_state"),
        ({"R": [1.0]}, "agents.R"),
        ({"R": [1.0, -1.0]}, "R"),
        ({"horizon": 2.5}, "horizon"),
        ({"typo_key": 1}, "typo_key"),
    ],
)
def test_bad_agent_configs_name_the_key(section, key):
    with pytest.raises(ConfigError, match=key):
        load_config({"agents": section})


def test_the_config_knows_the_solver_registrys_names_only():
    for name in SOLVERS:
        assert load_config({"agents": {"solver": name}}).agents.solver == name
    with pytest.raises(ConfigError, match="agents.solver='textbook'"):
        load_config({"agents": {"solver": "textbook"}})


def test_scenario_count_from_the_campi_garatti_bound():
    cfg = {"agents": {"n_scenarios": None, "violation_level": 0.2, "confidence": 0.01}}
    agent = make_agent("scenario", {**cfg, "agents": {**cfg["agents"], "n_particles": 100}})
    # nu N decision variables: 2 inputs of the bicycle over the horizon.
    expected = campi_garatti_scenarios(0.2, 0.01, 2 * AgentConfig().horizon)
    assert agent.problem.n_scenarios == expected
    assert load_config(cfg).scenario_count() == expected


def test_a_campi_garatti_count_beyond_the_limit_names_the_level():
    cfg = {"agents": {"n_scenarios": None, "violation_level": 1e-5, "confidence": 1e-3}}
    with pytest.raises(ConfigError, match="agents.violation_level=1e-05: must be >= "):
        load_config(cfg)


def test_scenarios_can_start_from_particles():
    cfg = {
        "env": {"max_steps": 4},
        "agents": {"scenario_initial_states": "particles", "n_scenarios": 6, "n_particles": 500},
    }
    actions, infos, est = run("scenario", cfg, seed=2)
    assert len(actions) == 4
    # Each scenario starts from its own particle: the predicted starts differ.
    starts = est[-1]["predicted"][:, 0, :]
    assert np.unique(starts[:, 0]).size > 1


def test_a_diverged_filter_restarts_around_the_measurement():
    agent = make_agent("pf", {"agents": {"n_particles": 500, "n_scenarios": 3}})
    agent.reset(seed=0)
    obs = np.array([0.0, 0.0, 1.0, np.pi / 4])
    agent.act(obs)
    assert not agent.last_info["filter_reset"]
    # A speed 3 m/s (20 measurement std) away from every particle: the cloud is lost.
    jump = obs + np.array([0.0, 0.0, 3.0, 0.0])
    agent.act(jump)
    assert agent.last_info["filter_reset"]
    assert agent.last_info["filter_resets"] == 1
    assert agent.last_info["estimate"][2] == pytest.approx(jump[2], abs=0.1)


# --------------------------------------------------------------------------- another system


def point_mass_world() -> tuple[LatentForceModel, QuadraticCost]:
    """A planar point mass pushed by a two-axis latent force, with a wall at p_y = 0.5 m."""

    def rhs(x, u, w):
        _, _, vx, vy = xp.unstack(x)
        ax, ay = xp.unstack(u)
        wx, wy = xp.unstack(w)
        return xp.stack([vx, vy, ax + wx - 0.2 * vx, ay + wy - 0.2 * vy])

    def wall(x):
        _, py, _, _ = xp.unstack(x)
        return xp.stack([py - 0.5])

    system = ControlSystem(
        name="point_mass",
        state_names=("p_x [m]", "p_y [m]", "v_x [m/s]", "v_y [m/s]"),
        input_names=("a_x [m/s^2]", "a_y [m/s^2]"),
        rhs=rhs,
        input_lower=[-2.0, -2.0],
        input_upper=[2.0, 2.0],
        constraints=wall,
        constraint_names=("wall [m]",),
        force_names=("w_x [m/s^2]", "w_y [m/s^2]"),
    )
    model = LatentForceModel(
        system,
        kernel=[gp.matern(1.5, 0.3, 2.0), gp.matern(2.5, 0.3, 3.0)],
        dt=0.1,
        process_noise_std=[1e-3, 1e-3, 1e-3, 1e-3],
    )
    cost = QuadraticCost(Q=[1.0, 1.0, 0.1, 0.1], R=[0.1, 0.1], x_goal=[3.0, 0.3, 0.0, 0.0])
    return model, cost


@pytest.mark.parametrize("name", ["nominal", "pf", "scenario", "scenario_particles"])
def test_agents_run_on_a_system_defined_in_this_file(name):
    model, cost = point_mass_world()
    std = np.full(4, 0.02)
    env = LatentForceEnv(
        model, cost, initial_state=[0.0, 0.0, 0.0, 0.0], measurement_std=std, max_steps=40
    )
    settings = AgentConfig(
        horizon=8,
        n_scenarios=20,
        n_particles=2000,
        Q=(1.0,) * 4,
        Qf=(1.0,) * 4,
        R=(0.1, 0.1),
        goal_state=(3.0, 0.3, 0.0, 0.0),
    )
    agent = AGENT_REGISTRY[name].agent_class(model, cost, settings, measurement_std=std)
    obs, _ = env.reset(seed=4)
    agent.reset(seed=5)
    for _ in range(40):
        obs, _, term, trunc, info = env.step(agent.act(obs))
        assert agent.last_info["status"]
        if term or trunc:
            break
    assert agent.last_info["W"].shape == (agent.problem.n_scenarios, 8, 2)
    # The controller moved the mass most of the way to the goal and kept it near the wall.
    x = env.true_state
    assert x[0] > 1.5, f"{name} stalled at p_x = {x[0]:.2f} m"
    assert np.max(info["constraint_excess"]) < 0.1
    if name != "nominal":
        assert agent.last_info["latent_force"].shape == (2,)


def test_a_filtering_agent_needs_measurement_noise():
    model, cost = point_mass_world()
    with pytest.raises(ValueError, match="measurement_std=.*must be all > 0"):
        ScenarioMPCAgent(
            model,
            cost,
            AgentConfig(Q=(1.0,) * 4, Qf=(1.0,) * 4, R=(0.1, 0.1)),
            measurement_std=[0.1, 0.1, 0.0, 0.1],
        )


# --------------------------------------------------------------------------- solve time limit


@pytest.mark.parametrize("solver", SOLVER_CASES)
def test_a_solve_that_reaches_max_solve_time_fails_and_the_agent_falls_back(solver):
    """Issue 15, case 5: a solve has a wall-clock limit (agents.max_solve_time); one that
    reaches it is a failed solve (IPOPT's status Maximum_WallTime_Exceeded) and the agent
    falls back, as on any failed solve."""
    cfg = {"env": {"max_steps": 3}, "agents": {"solver": solver, "max_solve_time": 1e-9}}
    actions, infos, est = run("nominal", cfg, max_steps=2)
    for rec in est:
        assert rec["status"] == "Maximum_WallTime_Exceeded"
        assert rec["success"] is False and rec["usable"] is False
        assert rec["fallback"] in ("previous_plan", "fallback")
    assert est[0]["fallback"] == "fallback"  # no plan yet: the system's fallback input
    assert np.all(np.isfinite(actions))


def test_max_solve_time_default_leaves_normal_solves_alone():
    assert AgentConfig().max_solve_time == 10.0
    _, _, est = run("nominal", {"env": {"max_steps": 2}}, max_steps=2)
    assert all(rec["success"] and rec["fallback"] == "" for rec in est)


@pytest.mark.parametrize("value", [0.0, -1.0, float("nan"), 3601.0, "10"])
def test_max_solve_time_out_of_range_is_refused(value):
    with pytest.raises(ConfigError, match=r"max_solve_time"):
        load_config({"agents": {"max_solve_time": value}})


def test_agents_solver_threads_reach_the_fast_solver_with_the_same_actions():
    """agents.solver_threads gives the fast solver's C library that many threads; the closed
    loop acts as with one (plans equal to rounding)."""
    cfg = {"env": {"max_steps": 4}, "agents": {"n_scenarios": 300, "solver": "fast"}}
    one, _, _ = run("scenario", cfg, max_steps=4)
    cfg["agents"]["solver_threads"] = 2
    agent = make_agent("scenario", cfg)
    assert agent.solver.options.threads == 2 and agent.solver.condensed.threads == 2
    two, _, est = run("scenario", cfg, max_steps=4)
    assert all(rec["success"] for rec in est)
    np.testing.assert_allclose(two, one, atol=1e-7)


@pytest.mark.parametrize(
    ("agents", "message"),
    [
        ({"solver_threads": 0}, r"solver_threads=0: must be an integer in \[1, 256\]"),
        ({"solver_threads": 1.5}, r"solver_threads=1.5: expected an integer"),
        ({"solver_threads": 2, "solver": "ipopt"}, r"must be 1 with solver 'ipopt'"),
    ],
)
def test_bad_solver_threads_are_refused_naming_the_field(agents, message):
    with pytest.raises(ConfigError, match=message):
        load_config({"agents": agents})


def test_a_fast_solver_horizon_beyond_its_practical_bound_is_refused_up_front():
    """Issue 15, case 5: at horizon 100 one fast-SQP iteration alone outlasts any solve limit
    (one step took 84 s against a 10 s limit), so such horizons are refused when read."""
    from controllers.config import FAST_MAX_HORIZON

    with pytest.raises(ConfigError, match=rf"agents.horizon=100: must be <= {FAST_MAX_HORIZON}"):
        load_config({"agents": {"horizon": 100, "solver": "fast"}})
    assert FAST_MAX_HORIZON == 50  # (measured to work with real-time iterations: docs/solvers.md)
    assert load_config({"agents": {"horizon": FAST_MAX_HORIZON}}).agents.horizon == 50


@pytest.mark.slow
def test_horizon_60_ipopt_step_ends_within_the_solve_time_limit():
    """Issue 15, case 5: long horizons took minutes for one MPC step; now one step ends after
    agents.max_solve_time (plus one iteration), with an unconverged solve whose plan is applied
    only when usable (else the fallback)."""
    cfg = {
        "env": {"max_steps": 2},
        "agents": {"horizon": 60, "max_solve_time": 0.05, "solver": "ipopt"},
    }
    _, _, est = run("nominal", cfg, max_steps=1)
    assert est[0]["status"] == "Maximum_WallTime_Exceeded"
    assert not est[0]["success"]
    # A stopped solve below its warm start is applied (usable); anything else falls back.
    assert est[0]["fallback"] == ("" if est[0]["usable"] else "fallback")
    assert est[0]["solve_time"] < 60.0  # generous: 2 s plus one iteration
