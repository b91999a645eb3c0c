"""Constraint back-off: every solver tightens the state constraints by the given amounts,
and the filtering agents size it from the estimate's spread along each constraint."""

from __future__ import annotations

import numpy as np
import pytest

from controllers.agents import make_agent
from controllers.config import load_config
from controllers.solvers import SOLVERS, make_solver

X0 = np.array([10.0, 1.2, 5.0, 0.3])
BACKOFF = np.tile([0.1, 0.1, 0.0, 0.0, 0.2, 0.2], (7, 1))  # [m, m, m, m, m/s, m/s]
OBS = np.array([0.0, 0.0, 1.0, np.pi / 4])  # the first observation of the agents' tests
UKF_AGENT = {"estimator": "ukf", "n_scenarios": 5}


# sqpmethod's JIT build takes 15-50 s: its case runs with the slow tests (CI runs them).
SOLVER_CASES = [pytest.param(s, marks=pytest.mark.slow) if s == "sqpmethod" else s for s in SOLVERS]


@pytest.fixture(scope="module")
def problem_and_data():
    problem = load_config("configs/paper.yaml").make_problem(n_scenarios=20, horizon=7)
    W = problem.model.sample_latent_forecasts(np.zeros((20, 3)), 7, np.random.default_rng(0))
    return problem, W


@pytest.mark.parametrize("name", SOLVER_CASES)
def test_every_solver_meets_the_tightened_constraints_at_the_same_optimum(name, problem_and_data):
    pytest.importorskip("csnlp") if name == "csnlp" else None
    problem, W = problem_and_data
    reference = make_solver(problem, "ipopt_multiple_shooting").solve(X0, W, backoff=BACKOFF)
    sol = make_solver(problem, name).solve(X0, W, backoff=BACKOFF)
    assert sol.success
    assert sol.objective == pytest.approx(problem.objective(X0, W, sol.u, BACKOFF), rel=1e-9)
    assert sol.objective == pytest.approx(reference.objective, rel=1e-6)
    X = problem.rollout(X0, W, sol.u)
    g = problem.constraint_values(X)  # untightened
    # No slack is needed here, so every constraint keeps at least its back-off as margin,
    # and the tightened problem costs more than the plain one (the back-off binds).
    assert sol.slack < 1e-6
    assert np.all(g + BACKOFF <= 1e-6)
    # Here the upper speed bound and both track edges are active: their margin is exactly
    # the back-off.
    assert np.max(g[:, :, 5]) == pytest.approx(-0.2, abs=1e-6)
    assert np.max(g[:, :, :2]) == pytest.approx(-0.1, abs=1e-6)
    plain = make_solver(problem, name).solve(X0, W)
    assert plain.objective < sol.objective - 1.0


def test_a_scalar_row_of_backoff_applies_to_every_step(problem_and_data):
    problem, W = problem_and_data
    solver = make_solver(problem, "fast")
    a = solver.solve(X0, W, backoff=BACKOFF[0])
    solver.reset()
    b = solver.solve(X0, W, backoff=BACKOFF)
    np.testing.assert_allclose(a.u, b.u, rtol=0.0, atol=1e-12)


@pytest.mark.parametrize(
    "backoff",
    [-np.ones(6), np.full(6, np.nan), np.ones(5), np.ones((8, 6)), np.array(["a"] * 6)],
    ids=["negative", "nan", "short", "long-horizon", "text"],
)
def test_a_bad_backoff_is_refused_naming_it(backoff, problem_and_data):
    problem, W = problem_and_data
    with pytest.raises(ValueError, match="backoff"):
        make_solver(problem, "fast").solve(X0, W, backoff=backoff)
    with pytest.raises(ValueError, match="backoff"):
        problem.objective(X0, W, np.zeros((7, 2)), backoff)


def agent_after_two_steps(backoff: object) -> tuple:
    """The scenario agent (UKF, 5 scenarios) with ``backoff`` after two observations, and its
    estimate's physical covariance and the constraint Jacobian at its mean."""
    agent = make_agent("scenario", {"agents": {"backoff": backoff, **UKF_AGENT}})
    agent.reset(seed=0)
    agent.act(OBS)
    agent.act(OBS + np.array([0.2, 0.2, 0.0, 0.0]))
    mean, cov = agent.estimator.mean[:4], agent.estimator.covariance[:4, :4]
    return agent, cov, agent.system.constraint_jacobian(mean)


def test_the_agent_backs_off_k_estimate_stds_along_each_constraint_gradient():
    agent, cov, J = agent_after_two_steps(2.0)
    expected = 2.0 * np.sqrt(np.diag(J @ cov @ J.T))
    np.testing.assert_allclose(agent.last_info["backoff"], expected, rtol=1e-12)
    # The speed bounds' gradient is the speed axis: their back-off is 2 speed stds.
    assert agent.last_info["backoff"][4] == pytest.approx(2.0 * np.sqrt(cov[2, 2]))
    assert np.all(expected > 0.0)
    # Without back-off the agent passes none.
    plain = make_agent("scenario", {"agents": UKF_AGENT})
    plain.reset(seed=0)
    plain.act(OBS)
    assert plain.last_info["backoff"] is None


def test_one_backoff_per_constraint_group():
    agent, cov, J = agent_after_two_steps([3.0, 0.0, 1.0])
    spread = np.sqrt(np.diag(J @ cov @ J.T))
    # Groups of the sine track: track (track_left, track_right), x (x_min, x_max), speed.
    k = np.array([3.0, 3.0, 0.0, 0.0, 1.0, 1.0])
    np.testing.assert_allclose(agent.last_info["backoff"], k * spread, rtol=1e-12)


@pytest.mark.parametrize("key", ["backoff", "robust"])
def test_a_backoff_of_the_wrong_length_names_the_groups(key):
    from lfm_env.config import ConfigError

    section = {"backoff": [1.0, 2.0]} if key == "backoff" else {"robust": {"backoff": [1, 2]}}
    name = "agents.backoff" if key == "backoff" else "agents.robust.backoff"
    with pytest.raises(ConfigError, match=rf"{name}=\[1.0, 2.0\]: must be one number or 3"):
        load_config({"agents": section})
    assert load_config({"agents": {"backoff": 2.5}}).agents.backoff == (2.5,)


def test_the_robust_agent_takes_its_own_estimator_backoff_and_forecast():
    cfg = {
        "agents": {
            "n_scenarios": 7,
            "robust": {"estimator": "rbpf", "n_particles": 300, "backoff": [2.0, 0.0, 1.0]},
        }
    }
    agent = make_agent("robust", cfg)
    assert agent.estimator.name == "rbpf" and agent.estimator.n_particles == 300
    assert agent.problem.n_scenarios == 1  # forecast "mean": one scenario
    agent.reset(seed=0)
    obs = np.array([0.0, 0.0, 1.0, np.pi / 4])
    agent.act(obs)
    info = agent.last_info
    z = info["estimate"][4:]
    np.testing.assert_allclose(info["W"][0], agent.model.mean_latent_forecast(z, 7))
    assert info["backoff"][2] == 0.0 and info["backoff"][0] > 0.0
    assert info["estimator"] == "rbpf"
    sampled = {"agents": {"n_scenarios": 7, "robust": {"forecast": "sampled"}}}
    assert make_agent("robust", sampled).problem.n_scenarios == 7
