"""The feedback scenario prediction: the law, its gains, the reference functions, the exact
rewrite every solver runs on, and what a solve without a feasible input returns.

A cart on a rail, defined in this file alone (``[p, v]`` [m, m/s], a force ``u`` [m/s^2]
inside +-1 and a latent force ``w`` [m/s^2], a wall ``p <= 1 m``), is linear, so its TV-LQR
gains can be checked against SciPy's discrete Riccati solution.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import scipy.linalg

from controllers.config import load_config
from controllers.feedback_law import (
    FeedbackLaw,
    feedback_law,
    nominal_inputs,
    nominal_rollout,
    tvlqr_gains,
)
from controllers.problem import EulerModel, MPCSolution, ScenarioProblem
from controllers.solvers import make_solver, solver_spec
from controllers.solvers.fast.compiled import CompiledScenarioSolver
from controllers.solvers.fast.solver import FastScenarioSolver
from controllers.solvers.feedback import (
    FeedbackScenarioSolver,
    augmented_data,
    augmented_problem,
)
from lfm_env.cost import QuadraticCost
from lfm_env.gp import matern
from lfm_env.model import LatentForceModel
from lfm_env.system import ControlSystem
from lfm_env.xp import xp
from tests.conftest import PAPER_CONFIG

DT = 0.1  # [s]
WALL = 1.0  # [m]


def cart_rhs(x, u, w):
    """``[p, v]`` [m, m/s] pushed by ``u + w`` [m/s^2]."""
    _, v = xp.unstack(x)
    (a,) = xp.unstack(u)
    (f,) = xp.unstack(w)
    return xp.stack([v, a + f])


def cart_wall(x):
    """``p - 1 <= 0`` [m]."""
    p, _ = xp.unstack(x)
    return xp.stack([p - WALL])


CART = ControlSystem(
    name="cart",
    state_names=("p [m]", "v [m/s]"),
    input_names=("a [m/s^2]",),
    force_names=("w [m/s^2]",),
    rhs=cart_rhs,
    input_lower=(-1.0,),
    input_upper=(1.0,),
    constraints=cart_wall,
    constraint_names=("wall [m]",),
)
CART_COST = QuadraticCost(Q=(1.0, 0.1), R=(0.5,), Qf=(5.0, 1.0), x_goal=(0.9, 0.0))
CART_MODEL = LatentForceModel(CART, kernel=matern(1.5, 0.05, 1.0), dt=DT)


def cart_problem(n: int = 12, ns: int = 20, prediction: str = "feedback") -> ScenarioProblem:
    return ScenarioProblem(
        CART_MODEL, CART_COST, horizon=n, n_scenarios=ns, slack_penalty=1e3, prediction=prediction
    )


def lqr_law(problem: ScenarioProblem, x0, W, rng: np.random.Generator, spread: float = 0.5):
    """The TV-LQR gains along the zero plan, with reference states moved at random."""
    law = feedback_law(problem, x0, W, np.zeros((problem.horizon, problem.nu)))
    return FeedbackLaw(law.K, law.r + rng.normal(0.0, spread, law.r.shape))


def simulate(problem: ScenarioProblem, x0, W, v, law) -> tuple[np.ndarray, np.ndarray]:
    """The stated law, scenario by scenario and step by step, through ``system.rhs``."""
    x0, W = problem.check_data(x0, W)
    X = np.empty((problem.n_scenarios, problem.horizon + 1, problem.nx))
    U = np.empty((problem.n_scenarios, problem.horizon, problem.nu))
    for s in range(problem.n_scenarios):
        x = x0[s].copy()
        X[s, 0] = x
        for k in range(problem.horizon):
            u = np.array(v[k], dtype=float)
            if k >= 1:
                u = u + law.K[k] @ (x - law.r[k])
            U[s, k] = u
            x = x + problem.dt * np.asarray(problem.system.rhs(x, u, W[s, k]), dtype=float)
            X[s, k + 1] = x
    return X, U


@pytest.fixture(scope="module")
def quadrotor_feedback() -> ScenarioProblem:
    cfg = load_config(PAPER_CONFIG.with_name("quadrotor.yaml"))
    return cfg.make_problem(n_scenarios=12, prediction="feedback")


# ----------------------------------------------------------------------------- the law


def test_the_law_refuses_feedback_at_the_first_step_and_bad_shapes() -> None:
    K = np.zeros((3, 1, 2))
    K[0, 0, 1] = 0.1
    with pytest.raises(ValueError, match=r"K\[0\] must be zero"):
        FeedbackLaw(K, np.zeros((3, 2)))
    with pytest.raises(ValueError, match="expected K"):
        FeedbackLaw(np.zeros((3, 1, 2)), np.zeros((4, 2)))
    with pytest.raises(ValueError, match="finite"):
        FeedbackLaw(np.full((3, 1, 2), np.nan), np.zeros((3, 2)))
    law = FeedbackLaw(np.zeros((3, 1, 2)), np.zeros((3, 2)))
    assert not law.K.flags.writeable
    with pytest.raises(ValueError, match=r"law.K has shape \(3, 1, 2\)"):
        cart_problem(n=4).objective(np.zeros(2), np.zeros((20, 4)), np.zeros((4, 1)), law=law)


def test_a_law_needs_a_feedback_problem_and_the_prediction_is_checked() -> None:
    open_loop = cart_problem(prediction="open_loop")
    law = FeedbackLaw.zero(open_loop)
    with pytest.raises(ValueError, match="prediction='open_loop'"):
        open_loop.rollout(np.zeros(2), np.zeros((20, 12)), np.zeros((12, 1)), law=law)
    with pytest.raises(ValueError, match=r"ScenarioProblem.prediction='closed': must be one of"):
        cart_problem(prediction="closed")


def test_tvlqr_gains_of_a_linear_system_reach_the_stationary_riccati_gain() -> None:
    problem = cart_problem(n=200, ns=1)
    A = np.array([[1.0, DT], [0.0, 1.0]])
    B = np.array([[0.0], [DT]])
    Q, R = CART_COST.Q, CART_COST.R
    P = scipy.linalg.solve_discrete_are(A, B, Q, R)
    K_inf = -np.linalg.solve(R + B.T @ P @ B, B.T @ P @ A)
    X, w = nominal_rollout(problem, np.zeros(2), np.zeros((1, 200)), np.zeros((200, 1)))
    K = tvlqr_gains(problem, X, np.zeros((200, 1)), w)
    assert K.shape == (200, 1, 2)
    np.testing.assert_array_equal(K[0], 0.0)
    np.testing.assert_allclose(K[1], K_inf, rtol=1e-9)
    # The last gain is the one-step LQR of the terminal weight.
    Qf = CART_COST.Qf
    np.testing.assert_allclose(K[-1], -np.linalg.solve(R + B.T @ Qf @ B, B.T @ Qf @ A))


def test_feedback_law_linearises_along_the_nominal_rollout_of_the_clipped_reference() -> None:
    problem = cart_problem(n=6, ns=4)
    rng = np.random.default_rng(1)
    x0 = rng.normal(0.0, 0.1, (4, 2))
    W = rng.normal(0.0, 0.3, (4, 6))
    u_ref = np.full((6, 1), 3.0)  # outside the bounds: clipped to 1
    law = feedback_law(problem, x0, W, u_ref)
    X, wbar = nominal_rollout(problem, x0, W, np.ones((6, 1)))
    np.testing.assert_allclose(law.r, X[:-1], rtol=0, atol=1e-15)
    np.testing.assert_allclose(wbar[:, 0], W.mean(axis=0))
    np.testing.assert_allclose(X[0], x0.mean(axis=0))
    # Applied to the nominal rollout, the reference plan gives back its inputs.
    np.testing.assert_allclose(nominal_inputs(problem, x0, W, np.ones((6, 1)), law), 1.0)


# ----------------------------------------------------------------------------- reference functions


@pytest.mark.parametrize("world", ["cart", "quadrotor"])
def test_the_feedback_rollout_is_the_closed_loop_simulated_scenario_by_scenario(
    world, quadrotor_feedback
) -> None:
    problem = cart_problem() if world == "cart" else quadrotor_feedback
    rng = np.random.default_rng(7)
    ns, n = problem.n_scenarios, problem.horizon
    # Every scenario from its own start (particles): the first input is still shared.
    x0 = problem.cost.x_goal + rng.normal(0.0, 0.2, (ns, problem.nx))
    W = rng.normal(0.0, 0.5, (ns, n, problem.nw))
    v = rng.uniform(problem.input_lower, problem.input_upper, (n, problem.nu))
    law = lqr_law(problem, x0, W, rng)
    assert np.abs(law.K[1:]).max() > 0.1
    X_sim, U_sim = simulate(problem, x0, W, v, law)
    np.testing.assert_allclose(problem.rollout(x0, W, v, law=law), X_sim, rtol=1e-12, atol=1e-12)
    U = problem.inputs(x0, W, v, law=law)
    np.testing.assert_allclose(U, U_sim, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(U[:, 0], np.broadcast_to(v[0], (ns, problem.nu)))
    # The augmented problem's own rollout (what every solver evaluates) is the same.
    aug = augmented_problem(problem)
    x0a, Wa = augmented_data(problem, x0, W, law)
    Xa = aug.rollout(x0a, Wa, v)
    np.testing.assert_allclose(Xa[:, :, : problem.nx], X_sim, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(Xa[:, 1:, problem.nx :], U_sim, rtol=1e-12, atol=1e-12)
    # ... and so is the fast solver's compiled rollout of its returned plan.
    sol = make_solver(problem, "fast", max_iter=1).solve(x0, W, u_guess=v, law=law)
    X_plan, _ = simulate(problem, x0, W, sol.u, law)
    np.testing.assert_allclose(sol.predicted, X_plan, rtol=1e-10, atol=1e-10)


def test_with_zero_gains_the_feedback_objective_is_the_open_loop_objective() -> None:
    cfg = load_config(PAPER_CONFIG)
    open_loop = cfg.make_problem(n_scenarios=40)
    feedback = dataclasses.replace(open_loop, prediction="feedback")
    rng = np.random.default_rng(3)
    W = rng.normal(0.0, 2.0, (40, open_loop.horizon))  # some scenarios need slack
    x0 = np.array([10.0, 2.0, 5.0, 0.3])
    zero = FeedbackLaw.zero(feedback)
    for _ in range(5):
        u = rng.uniform(open_loop.input_lower, open_loop.input_upper, (open_loop.horizon, 2))
        J = open_loop.objective(x0, W, u)
        assert feedback.objective(x0, W, u, law=zero) == pytest.approx(J, rel=1e-13)
        assert feedback.objective(x0, W, u) == J  # no law: the open-loop function
        np.testing.assert_array_equal(
            feedback.rollout(x0, W, u, law=zero), open_loop.rollout(x0, W, u)
        )
    # Inside the bounds no input slack; outside, each side of each step counts once.
    U = np.zeros((40, open_loop.horizon, 2))
    U[3, 2, 0] = open_loop.input_upper[0] + 0.5
    U[7, 2, 0] = open_loop.input_upper[0] + 0.25
    U[1, 4, 1] = open_loop.input_lower[1] - 0.125
    U[2, 0, 1] = open_loop.input_lower[1] - 9.0  # step 0: v_0, hard-bounded, not counted
    slack = feedback.input_slack(U)
    assert slack.shape == (open_loop.horizon - 1, 2, 2)
    assert slack[1, 0, 0] == pytest.approx(0.5) and slack[3, 1, 1] == pytest.approx(0.125)
    assert slack.sum() == pytest.approx(0.625)


def test_the_rewrite_has_the_feedback_objective(quadrotor_feedback) -> None:
    problem = quadrotor_feedback
    rng = np.random.default_rng(11)
    ns, n = problem.n_scenarios, problem.horizon
    x0 = problem.cost.x_goal + rng.normal(0.0, 0.3, (ns, problem.nx))
    W = rng.normal(0.0, 1.0, (ns, n, problem.nw))
    law = lqr_law(problem, x0, W, rng, spread=2.0)  # far references: input slack
    aug = augmented_problem(problem)
    x0a, Wa = augmented_data(problem, x0, W, law)
    backoff = rng.uniform(0.0, 0.05, (n, problem.ng))
    ba = np.concatenate([backoff, np.zeros((n, 2 * problem.nu))], axis=1)
    for _ in range(3):
        v = rng.uniform(problem.input_lower, problem.input_upper, (n, problem.nu))
        U = problem.inputs(x0, W, v, law=law)
        assert problem.input_slack(U).sum() > 0.0
        J = problem.objective(x0, W, v, backoff=backoff, law=law)
        assert aug.objective(x0a, Wa, v, backoff=ba) == pytest.approx(J, rel=1e-13)


# ----------------------------------------------------------------------------- solvers


@pytest.mark.parametrize("native", [True, False])
def test_the_fast_solver_and_the_rewrite_keep_the_solvers_protocol(native) -> None:
    problem = cart_problem(n=5, ns=4)
    if native:  # make_solver's: the fast SQP on the feedback problem itself
        solver = make_solver(problem, "fast")
        assert isinstance(solver, FastScenarioSolver) and solver.condensed.feedback
    else:  # the exact rewrite every other solver runs through
        solver = FeedbackScenarioSolver(problem, solver_spec("fast"))
        assert solver.augmented.prediction == "open_loop"
        assert isinstance(solver.augmented.model, EulerModel)
        assert solver.augmented.nx == 3 and solver.augmented.ng == 3
        assert isinstance(make_solver(problem, "ipopt"), FeedbackScenarioSolver)
    rng = np.random.default_rng(0)
    x0, W = np.array([0.0, 0.0]), rng.normal(0.0, 0.5, (4, 5))
    first = solver.solve(x0, W)
    assert first.extra["reference"] == "open_loop_solve" and first.usable
    assert first.law is not None and first.nominal_u.shape == (5, 1)
    assert first.plan is first.nominal_u and first.plan[0] == first.u[0]
    assert first.objective == pytest.approx(problem.objective(x0, W, first.u, law=first.law))
    second = solver.solve(x0, W)  # the previous nominal plan, shifted, is the reference
    assert second.extra["reference"] == "previous_plan"
    solver.reset()
    assert solver.solve(x0, W).extra["reference"] == "open_loop_solve"
    given = solver.solve(x0, W, law=first.law, u_guess=first.u)
    assert given.extra["reference"] == "u_guess" and given.law is first.law


def _cart_data(problem: ScenarioProblem, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    x0 = np.array([0.2, 0.4]) + rng.normal(0.0, 0.05, (problem.n_scenarios, 2))
    return x0, rng.normal(0.0, 0.8, (problem.n_scenarios, problem.horizon))


@pytest.mark.parametrize("seed", [0, 1])
def test_with_zero_gains_every_solver_reaches_the_open_loop_optimum(seed) -> None:
    feedback = cart_problem(n=10, ns=15)
    open_loop = dataclasses.replace(feedback, prediction="open_loop")
    x0, W = _cart_data(feedback, seed)
    ref = make_solver(open_loop, "ipopt", ipopt_options={"tol": 1e-10}).solve(x0, W)
    zero = FeedbackLaw.zero(feedback)
    for name in ("fast", "ipopt"):
        sol = make_solver(feedback, name).solve(x0, W, law=zero, u_guess=ref.u)
        assert sol.success, (name, sol.status)
        assert sol.objective == pytest.approx(ref.objective, rel=1e-6), name


# ----------------------------------------------------------------------------- no feasible input


def test_a_problem_infeasible_for_every_input_ends_with_a_usable_plan() -> None:
    """The latent force (3 m/s^2 towards the wall) beats the input (1 m/s^2): every
    scenario hits the wall whatever the plan; the solve ends with the plan of least slack,
    converged, and when stopped early (one iteration) with a usable plan, status
    ``Maximum_Iterations_Exceeded``."""
    for prediction in ("open_loop", "feedback"):
        problem = cart_problem(n=10, ns=8, prediction=prediction)
        x0 = np.array([0.5, 0.5])
        W = np.full((8, 10), 3.0) + np.linspace(0.0, 0.5, 8)[:, None]
        sol = make_solver(problem, "fast").solve(x0, W)
        assert sol.success and sol.usable, sol.status
        assert sol.slack > 0.1
        assert sol.u[0, 0] == pytest.approx(-1.0, abs=1e-6)  # full braking now
        early = make_solver(problem, "fast", max_iter=1).solve(x0, W)
        assert early.status == "Maximum_Iterations_Exceeded"
        assert not early.success and early.usable
        assert early.objective < problem.objective(x0, W, np.zeros((10, 1)), law=early.law)
        # No time for a single step: nothing usable (the agent falls back).
        none = make_solver(problem, "fast", max_time=1e-9).solve(x0, W)
        assert none.status == "Maximum_WallTime_Exceeded" and not none.usable


def test_usable_defaults_to_success_and_needs_a_finite_plan() -> None:
    def solution(u, success, usable=None):
        return MPCSolution(u, 1.0, 0.0, "s", success, 0.0, 1, usable=usable)

    assert solution(np.zeros((2, 1)), True).usable
    assert not solution(np.zeros((2, 1)), False).usable
    assert solution(np.zeros((2, 1)), False, usable=True).usable
    assert not solution(np.full((2, 1), np.nan), True).usable


# ----------------------------------------------------------------------------- agents


def _check_feedback_steps(agent, env, steps: int, seed: int = 0) -> list[dict]:
    obs, _ = env.reset(seed=seed)
    agent.reset(seed=seed)
    infos = []
    for _ in range(steps):
        action = agent.act(obs)
        info = agent.last_info
        infos.append(info)
        assert info["usable"] and info["fallback"] == ""
        # The applied input is v_0, which the nominal plan kept starts with.
        np.testing.assert_array_equal(action, info["plan"][0])
        obs, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            break
    references = [i["solver_extra"]["reference"] for i in infos]
    assert references[0] == "open_loop_solve"
    assert set(references[1:]) == {"previous_plan"}
    return infos


@pytest.mark.parametrize(
    ("config", "agent"),
    [
        ("paper.yaml", "scenario"),
        ("paper.yaml", "robust"),
        ("quadrotor.yaml", "scenario_particles"),
        ("quadrotor.yaml", "robust"),
    ],
)
def test_the_config_gives_every_scenario_agent_the_feedback_prediction(config, agent) -> None:
    import gymnasium as gym

    import lfm_env  # noqa: F401  (registers the env ids)
    from controllers.agents import make_agent

    cfg = load_config(PAPER_CONFIG.with_name(config))
    agents = dataclasses.replace(
        cfg.agents,
        prediction="feedback",
        n_scenarios=20,
        n_particles=500,
        robust=dataclasses.replace(cfg.agents.robust, forecast="sampled", n_particles=500),
    )
    cfg = dataclasses.replace(cfg, agents=agents)
    built = make_agent(agent, cfg)
    assert built.problem.prediction == "feedback"
    # the agents' default solver, fast_c, solves the feedback problem natively
    assert isinstance(built.solver, CompiledScenarioSolver) and built.solver.feedback
    env = gym.make(cfg.env_id, config=cfg.env)
    try:
        infos = _check_feedback_steps(built, env, steps=6)
    finally:
        env.close()
    assert infos[-1]["predicted"].shape == (20, cfg.agents.horizon + 1, cfg.make_system().nx)


def test_a_system_defined_here_runs_the_feedback_agent_in_its_env() -> None:
    from controllers.agents.mpc import ScenarioMPCAgent
    from controllers.config import AgentConfig
    from lfm_env.env import LatentForceEnv

    env = LatentForceEnv(
        CART_MODEL, CART_COST, initial_state=np.zeros(2), measurement_std=[0.01, 0.01]
    )
    settings = AgentConfig(
        horizon=10, n_scenarios=15, n_particles=300, prediction="feedback", max_iter=150
    )
    agent = ScenarioMPCAgent(CART_MODEL, CART_COST, settings, measurement_std=[0.01, 0.01])
    infos = _check_feedback_steps(agent, env, steps=25, seed=3)
    # It heads for the goal at 0.9 m and stays behind the wall at 1 m.
    positions = [i["estimate"][0] for i in infos]
    assert positions[-1] > 0.5 and max(positions) < WALL + 0.05


def test_the_config_names_the_prediction_field() -> None:
    from controllers.config import AgentConfig
    from lfm_env.config import ConfigError

    with pytest.raises(ConfigError, match=r"prediction='closed_loop': must be one of"):
        AgentConfig(prediction="closed_loop")
