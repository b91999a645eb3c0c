"""The ``dompc`` agent (:mod:`controllers.agents.dompc`): do-mpc's robust multi-stage MPC.

* Its plan on recorded problems is a hand-built do-mpc's (written here with do-mpc's
  high-level API, independently of the agent's code), and its NLP is the documented one:
  each branch's predicted states are the project's rollout of its inputs under the forecast
  plus the branch's offset, and do-mpc's objective is the branches' average cost plus the
  documented slack penalty.
* It runs paper and quadrotor episodes through ``gym.make``'s step API.
* Without do-mpc, building it raises one line naming the extra.

The tests that run do-mpc are skipped when it is not installed (it is the ``peers`` extra).
"""

from __future__ import annotations

import sys
import warnings
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import lfm_env  # noqa: F401  (registers the envs)
from controllers.agents.dompc import (
    MISSING_DO_MPC,
    DoMpcAgent,
    do_mpc_installed,
    import_do_mpc,
    make_dompc_agent,
    make_dompc_constant_agent,
)
from controllers.config import load_config
from controllers.problem import ScenarioProblem
from lfm_env.config import ConfigError

ROOT = Path(__file__).resolve().parents[2]
PAPER = ROOT / "configs" / "paper.yaml"
QUADROTOR = ROOT / "configs" / "quadrotor.yaml"
RECORDED = dict(np.load(ROOT / "tests" / "data" / "recorded_problems.npz"))
# One problem without slack (seed 0, step 25) and one whose force is beyond the braking
# authority, so the plan needs slack (seed 4, step 21).
PROBLEMS = [0, 9]
SPREAD = 2.0


def _do_mpc():
    try:
        return import_do_mpc()
    except ImportError:
        pytest.skip("do-mpc is not installed (the peers extra)")


@pytest.fixture(scope="module")
def paper():
    return load_config(PAPER)


@pytest.fixture(scope="module")
def agent(paper) -> DoMpcAgent:
    _do_mpc()
    return make_dompc_agent(paper)


def _recorded(i: int, horizon: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``x0``, a force forecast ``(N, 1)`` (the recorded scenarios' mean path) and the
    force's std ``(1,)`` (their spread at the horizon's end)."""
    W = RECORDED["W"][i]
    assert W.shape[1] == horizon
    return RECORDED["x0"][i], W.mean(axis=0), W[:, -1].std(axis=0)


def _hand_built(config, W: np.ndarray, std: np.ndarray, x0: np.ndarray) -> np.ndarray:
    """do-mpc built by hand on the same problem (high-level API); its nominal plan (N, nu)."""
    do_mpc = _do_mpc()
    model, a = config.make_model(), config.agents
    system, dt, N = model.system, model.dt, a.horizon
    nx, nu = system.nx, system.nu
    Q, R, Qf = np.asarray(a.Q), np.asarray(a.R), np.asarray(a.Qf)  # diagonal weights
    goal = config.make_cost().x_goal
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        m = do_mpc.model.Model("discrete")
        xs = m.set_variable("_x", "state", shape=(nx, 1))
        us = m.set_variable("_u", "input", shape=(nu, 1))
        ws = m.set_variable("_tvp", "forecast", shape=(1, 1))
        ds = m.set_variable("_p", "offset", shape=(1, 1))
        m.set_rhs("state", xs + dt * system.rhs(xs, us, ws + ds))
        m.setup()
        x, u = m.x["state"], m.u["input"]
        x_next = x + dt * system.rhs(x, u, m.tvp["forecast"] + m.p["offset"])
        e = x - goal
        lterm = sum(Q[i] * e[i] ** 2 for i in range(nx)) + sum(R[j] * u[j] ** 2 for j in range(nu))
        mterm = sum(Qf[i] * e[i] ** 2 for i in range(nx))
        mpc = do_mpc.controller.MPC(m)
        mpc.set_param(n_horizon=N, n_robust=1, t_step=dt, store_full_solution=False)
        mpc.settings.supress_ipopt_output()
        mpc.set_objective(lterm=lterm, mterm=mterm)
        mpc.set_rterm(input=0.0)
        mpc.bounds["lower", "_u", "input"] = system.input_lower
        mpc.bounds["upper", "_u", "input"] = system.input_upper
        mpc.set_nl_cons(
            "g",
            system.constraints(x_next),
            ub=0.0,
            soft_constraint=True,
            penalty_term_cons=a.slack_penalty / 3,
        )
        s = float(SPREAD * std[0])
        mpc.set_uncertainty_values(offset=[0.0, s, -s])
        tvp = mpc.get_tvp_template()
        for k in range(N + 1):
            tvp["_tvp", k, "forecast"] = W[min(k, N - 1), 0]
        mpc.set_tvp_fun(lambda t: tvp)
        mpc.setup()
        mpc.x0 = x0
        mpc.u0 = 0.5 * (system.input_lower + system.input_upper)
        mpc.set_initial_guess()
        mpc.make_step(x0)
    assert mpc.solver_stats["success"]
    return np.array([mpc.opt_x_num["_u", k, 0].full().ravel() for k in range(N)])


@pytest.mark.parametrize("i", PROBLEMS, ids=[f"problem{i}" for i in PROBLEMS])
def test_plan_is_a_hand_built_do_mpc_plan(agent: DoMpcAgent, paper, i: int) -> None:
    x0, W, std = _recorded(i, agent.horizon)
    agent.reset(seed=0)  # a fresh initial guess, as the hand-built one
    sol = agent.solve(x0, W, std)
    assert sol.success, sol.status
    reference = _hand_built(paper, W, std, x0)
    np.testing.assert_allclose(sol.u, reference, rtol=0.0, atol=1e-9)  # seen: <= 4e-13


@pytest.mark.parametrize("i", PROBLEMS, ids=[f"problem{i}" for i in PROBLEMS])
def test_nlp_is_the_documented_one(agent: DoMpcAgent, paper, i: int) -> None:
    """Every branch follows the project's physics under the forecast plus its offset; the
    objective is the branches' mean cost plus the slack penalty of the module docstring."""
    x0, W, std = _recorded(i, agent.horizon)
    agent.reset(seed=0)
    sol = agent.solve(x0, W, std)
    offsets, U = sol.extra["offsets"], sol.extra["branch_inputs"]
    S, N = agent.n_branches, agent.horizon
    np.testing.assert_allclose(offsets[:, 0], [0.0, SPREAD * std[0], -SPREAD * std[0]])
    np.testing.assert_allclose(U[:, 0], np.broadcast_to(U[0, 0], U[:, 0].shape))  # u_0 shared
    problem = ScenarioProblem(agent.model, agent.cost, horizon=N, n_scenarios=1)
    X = np.concatenate([problem.rollout(x0, (W + d)[None], U[b]) for b, d in enumerate(offsets)])
    np.testing.assert_allclose(sol.predicted, X, rtol=0.0, atol=1e-6)
    cost = agent.cost
    mean_cost = np.mean(
        [np.sum(cost.stage_cost(X[b, :-1], U[b])) + cost.terminal_cost(X[b, -1]) for b in range(S)]
    )
    excess = np.maximum(agent.system.constraint_values(X[:, 1:]), 0.0)  # (S, N, ng)
    penalty = paper.agents.slack_penalty * (excess[:, 0].max(0).sum() + excess[:, 1:].sum() / S)
    expected = mean_cost + penalty
    assert sol.objective == pytest.approx(expected, rel=1e-6, abs=1e-6)
    if RECORDED["slack"][i] > 1.0:
        assert sol.slack > 0.1  # the force is beyond the braking authority


@pytest.mark.parametrize("config", [PAPER, QUADROTOR], ids=["paper", "quadrotor"])
def test_runs_episodes_through_the_step_api(config: Path) -> None:
    _do_mpc()
    cfg = load_config(config)
    agent = make_dompc_agent(cfg)
    system = agent.system
    env = gym.make(cfg.env_id, config=cfg.env)
    obs, _ = env.reset(seed=3)
    agent.reset(seed=4)
    for _ in range(10):
        action = agent.act(obs)
        assert action.shape == (system.nu,)
        assert np.all(np.isfinite(action))
        assert np.all(action >= system.input_lower) and np.all(action <= system.input_upper)
        info = agent.last_info
        assert info["solve_time"] > 0.0 and info["estimator"] == "ukf"
        assert info["predicted"].shape == (3, agent.horizon + 1, system.nx)
        assert info["latent_force"].shape == info["latent_force_std"].shape == (1,)
        obs, _, terminated, truncated, _ = env.step(action)
        assert not (terminated or truncated)
    assert info["success"] and info["fallback"] == ""


def test_a_force_of_two_components_gets_five_branches() -> None:
    """The README's point mass (``nw = 2``): branches 0 and ``+- spread std_j e_j``; the
    agent drives it toward the goal along the wall."""
    _do_mpc()
    from controllers.config import AgentConfig
    from lfm_env import gp
    from lfm_env.cost import QuadraticCost
    from lfm_env.env import LatentForceEnv
    from lfm_env.model import LatentForceModel
    from lfm_env.system import ControlSystem
    from lfm_env.xp import xp

    def rhs(x, u, w):
        px, py, vx, vy = xp.unstack(x)
        ax, ay = xp.unstack(u)
        wx, wy = xp.unstack(w)
        return xp.stack([vx, vy, ax + wx, ay + wy])

    def keep_out(x):
        px, py, vx, vy = xp.unstack(x)
        return xp.stack([py - 0.5, vx - 1.5])

    system = ControlSystem(
        name="point_mass",
        state_names=("p_x [m]", "p_y [m]", "v_x [m/s]", "v_y [m/s]"),
        input_names=("a_x [m/s^2]", "a_y [m/s^2]"),
        rhs=rhs,
        input_lower=[-2.0, -2.0],
        input_upper=[2.0, 2.0],
        constraints=keep_out,
        constraint_names=("wall [m]", "speed_x [m/s]"),
        force_names=("w_x [m/s^2]", "w_y [m/s^2]"),
    )
    model = LatentForceModel(
        system,
        kernel=[gp.matern(1.5, 0.3, 2.0), gp.matern(2.5, 0.3, 3.0)],
        dt=0.1,
        process_noise_std=[1e-3] * 4,
    )
    cost = QuadraticCost(Q=[1, 1, 0.1, 0.1], R=[0.1, 0.1], x_goal=[3.0, 0.3, 0.0, 0.0])
    std = [0.02] * 4
    env = LatentForceEnv(model, cost, initial_state=np.zeros(4), measurement_std=std)
    agent = DoMpcAgent(model, cost, AgentConfig(horizon=10), measurement_std=std)
    assert agent.n_branches == 5
    obs, _ = env.reset(seed=0)
    agent.reset(seed=1)
    for _ in range(40):
        obs, *_ = env.step(agent.act(obs))
    info = agent.last_info
    s = SPREAD * info["latent_force_std"]
    np.testing.assert_allclose(
        info["solver_extra"]["offsets"],
        [[0, 0], [s[0], 0], [-s[0], 0], [0, s[1]], [0, -s[1]]],
    )
    assert info["predicted"].shape == (5, 11, 4) and info["success"]
    assert env.true_state[0] > 1.5  # most of the way to p_x = 3 m in 4 s
    assert np.max(system.constraint_excess(env.true_state)) < 0.1


def test_without_do_mpc_asking_for_it_is_one_line_naming_the_extra(monkeypatch, paper) -> None:
    from controllers.agents import check_agent_config, make_agent
    from experiments.evaluation import evaluate

    monkeypatch.setitem(sys.modules, "do_mpc", None)  # import do_mpc -> ImportError
    assert not do_mpc_installed()
    with pytest.raises(ImportError) as exc:
        make_dompc_agent(paper)
    assert str(exc.value) == MISSING_DO_MPC
    assert "\n" not in str(exc.value) and "lfm-scenario-mpc[peers]" in str(exc.value)
    # By its registered name: the registry's check, before anything is built.
    for ask in (lambda: check_agent_config("dompc", paper), lambda: make_agent("dompc", paper)):
        with pytest.raises(ConfigError) as exc:
            ask()
        assert str(exc.value) == MISSING_DO_MPC
    with pytest.raises(ConfigError, match=r"^dompc needs do-mpc: pip install"):
        evaluate(["nominal", "dompc"], seeds=[0], config=paper, progress=False, record=False)
    # A user factory is built once before the first episode: the same line, named.
    with pytest.raises(
        ValueError, match=r"dompc needs do-mpc: pip install 'lfm-scenario-mpc\[peers\]'"
    ):
        evaluate([make_dompc_constant_agent], seeds=[0], config=paper, progress=False, record=False)


def test_without_do_mpc_the_command_line_says_it_in_one_line(monkeypatch, capsys, tmp_path):
    from experiments.cli import evaluate_main

    monkeypatch.setitem(sys.modules, "do_mpc", None)
    with pytest.raises(SystemExit) as exit_:
        evaluate_main(["--agents", "dompc", "--seeds", "0", "--out", str(tmp_path / "r")])
    assert exit_.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == f"lfm-evaluate: error: {MISSING_DO_MPC}"
    assert not (tmp_path / "r").exists()


def test_the_registered_dompc_is_the_peer_agent(paper) -> None:
    from controllers.agents import AGENT_REGISTRY, make_agent

    spec = AGENT_REGISTRY["dompc"]
    assert spec.agent_class is DoMpcAgent and spec.needs_measurement_noise
    assert spec.label == "do-mpc multi-stage MPC (peer, UKF)"
    assert list(AGENT_REGISTRY)[-1] == "dompc"  # after the project's agents
    _do_mpc()
    agent = make_agent("dompc", paper)
    assert isinstance(agent, DoMpcAgent) and agent.estimator.name == "ukf"
