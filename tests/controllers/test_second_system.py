"""A second system, defined in this file alone, through the whole generic stack.

A point mass in the plane with quadratic air drag, pushed by a latent force with two
components (one GP per axis), below a wall ``p_y <= 1 m`` and with a speed bound. Nothing
else in the project knows it: the scenario problem, every solver, the particle filter and
the generic env must work from its :class:`ControlSystem` alone. Variants: a scalar force
on the x axis (``nw = 1``) and no state constraints (``ng = 0``).
"""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
from gymnasium.wrappers import TimeLimit

from controllers.estimators.particle_filter import ParticleFilter, gaussian_log_likelihood
from controllers.problem import ScenarioProblem, largest_local_descent
from controllers.solvers import make_solver
from lfm_env.cost import QuadraticCost
from lfm_env.env import LatentForceEnv
from lfm_env.gp import matern
from lfm_env.model import LatentForceModel, psd_factor
from lfm_env.system import ControlSystem
from lfm_env.xp import xp

try:
    import csnlp  # noqa: F401

    HAS_CSNLP = True
except ImportError:
    HAS_CSNLP = False

# ----------------------------------------------------------------------------- the system

DRAG = 0.2  # [1/m] quadratic drag coefficient
WALL = 1.0  # [m] the wall p_y <= WALL
SPEED_MAX = 1.5  # [m/s]
ACCEL_MAX = 3.0  # [m/s^2] per axis
DT = 0.1  # [s]


def drag(vx, vy):
    """Quadratic drag ``-c |v| v`` [m/s^2], smooth at rest."""
    speed = xp.sqrt(vx * vx + vy * vy + 1e-4)
    return -DRAG * speed * vx, -DRAG * speed * vy


def point_mass_rhs(x, u, w):
    """``[p_x, p_y, v_x, v_y]`` [m, m, m/s, m/s] pushed by ``u`` and a force on both axes."""
    _, _, vx, vy = xp.unstack(x)
    ax, ay = xp.unstack(u)
    wx, wy = xp.unstack(w)
    dx, dy = drag(vx, vy)
    return xp.stack([vx, vy, ax + wx + dx, ay + wy + dy])


def point_mass_rhs_x_force(x, u, w):
    """The same point mass with a scalar force along x only."""
    _, _, vx, vy = xp.unstack(x)
    ax, ay = xp.unstack(u)
    (wx,) = xp.unstack(w)
    dx, dy = drag(vx, vy)
    return xp.stack([vx, vy, ax + wx + dx, ay + dy])


def point_mass_constraints(x):
    """The wall ``p_y - 1 <= 0`` [m] and the speed bound ``|v|^2 - 1.5^2 <= 0`` [m^2/s^2]."""
    _, py, vx, vy = xp.unstack(x)
    return xp.stack([py - WALL, vx * vx + vy * vy - SPEED_MAX**2])


def point_mass(nw: int = 2, constrained: bool = True) -> ControlSystem:
    constraints = (
        dict(
            constraints=point_mass_constraints,
            constraint_names=("wall [m]", "speed [m^2/s^2]"),
        )
        if constrained
        else {}
    )
    return ControlSystem(
        name="point_mass",
        state_names=("p_x [m]", "p_y [m]", "v_x [m/s]", "v_y [m/s]"),
        input_names=("a_x [m/s^2]", "a_y [m/s^2]"),
        force_names=("w_x [m/s^2]", "w_y [m/s^2]") if nw == 2 else ("w_x [m/s^2]",),
        rhs=point_mass_rhs if nw == 2 else point_mass_rhs_x_force,
        input_lower=(-ACCEL_MAX, -ACCEL_MAX),
        input_upper=(ACCEL_MAX, ACCEL_MAX),
        **constraints,
    )


FORCE_STD = 1.0  # [m/s^2] prior std of each force component


def point_mass_model(system: ControlSystem) -> LatentForceModel:
    kernels = [matern(1.5, FORCE_STD**2, 2.0), matern(2.5, FORCE_STD**2, 3.0)][: system.nw]
    return LatentForceModel(
        system, kernel=kernels, dt=DT, process_noise_std=[0.01, 0.01, 0.03, 0.03]
    )


# The goal lies beyond the wall, so the wall is active at the optimum.
COST = QuadraticCost(
    Q=(1.0, 1.0, 0.1, 0.1), Qf=(5.0, 5.0, 0.5, 0.5), R=(0.1, 0.1), x_goal=(2.0, 1.3, 0.0, 0.0)
)

VARIANTS = {
    "two_forces": dict(nw=2, constrained=True),
    "scalar_force": dict(nw=1, constrained=True),
    "unconstrained": dict(nw=2, constrained=False),
}
N, NS = 6, 20


@pytest.fixture(scope="module", params=sorted(VARIANTS))
def problem(request) -> ScenarioProblem:
    model = point_mass_model(point_mass(**VARIANTS[request.param]))
    return ScenarioProblem(model, COST, horizon=N, n_scenarios=NS, slack_penalty=1.0e3)


def sample_forces(model: LatentForceModel, seed: int, ns: int = NS) -> np.ndarray:
    """Scenario forces ``(Ns, N, nw)`` drawn from the model from stationary latent states."""
    rng = np.random.default_rng(seed)
    factor = psd_factor(model.stationary_latent_covariance())
    z0 = rng.standard_normal((ns, model.latent_dim)) @ factor.T
    return model.sample_latent_forecasts(z0, N, rng)


SOLVER_NAMES = ("fast", "ipopt", "ipopt_multiple_shooting") + (("csnlp",) if HAS_CSNLP else ())
# Starts [m, m, m/s, m/s]: in open space; heading for the wall; too close and too fast to
# stop before it (slack needed); above the speed bound (slack needed).
STARTS = {
    "open": np.array([0.0, 0.0, 0.5, 0.0]),
    "towards_wall": np.array([0.0, 0.5, 0.8, 0.8]),
    "wall_breach": np.array([0.0, 0.97, 0.3, 1.2]),
    "overspeed": np.array([0.0, 0.0, 2.2, 0.2]),
}


# ----------------------------------------------------------------------------- the system itself


def test_definition_dimensions_and_casadi_agree_with_numpy() -> None:
    system = point_mass()
    assert (system.nx, system.nu, system.nw, system.ng) == (4, 2, 2, 2)
    assert system.constraint_labels == ("wall", "speed")
    assert point_mass(nw=1).nw == 1 and point_mass(constrained=False).ng == 0
    rng = np.random.default_rng(0)
    x, u, w = rng.normal(size=(3, 4)), rng.normal(size=(3, 2)), rng.normal(size=(3, 2))
    step = system.casadi_step(DT)
    g = system.casadi_constraints()
    for i in range(3):
        np.testing.assert_allclose(
            step(x[i], u[i], w[i]).full().ravel(),
            system.euler_step(x[i], u[i], w[i], DT),
            rtol=1e-14,
        )
        np.testing.assert_allclose(
            g(x[i]).full().ravel(), system.constraint_values(x[i]), rtol=1e-14
        )


# ----------------------------------------------------------------------------- solvers


@pytest.fixture(scope="module")
def solvers(problem: ScenarioProblem) -> dict:
    # Tight IPOPT tolerances: the agreement checked below is 1e-6 relative.
    ipopt = {"ipopt_options": {"tol": 1e-10}}
    return {
        name: make_solver(problem, name, **({} if name == "fast" else ipopt))
        for name in SOLVER_NAMES
    }


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("start", sorted(STARTS))
def test_solvers_agree_on_sampled_scenarios(
    problem: ScenarioProblem, solvers: dict, start: str, seed: int
) -> None:
    x0 = STARTS[start]
    W = sample_forces(problem.model, seed)
    if problem.nw == 1:  # the (Ns, N) form of a scalar force is accepted too
        W = W[:, :, 0]
    sols = {}
    for name, solver in solvers.items():
        solver.reset()
        sol = solver.solve(x0, W)
        assert sol.success, (name, sol.status)
        assert sol.u.shape == (N, problem.nu)
        assert np.all(sol.u >= problem.input_lower) and np.all(sol.u <= problem.input_upper)
        assert sol.objective == pytest.approx(problem.objective(x0, W, sol.u), rel=1e-12)
        np.testing.assert_allclose(sol.predicted, problem.rollout(x0, W, sol.u), atol=1e-12)
        sols[name] = sol
    objectives = {name: sol.objective for name, sol in sols.items()}
    best = min(objectives.values())
    for value in objectives.values():
        assert value == pytest.approx(best, rel=1e-6), objectives
    ref = sols["ipopt_multiple_shooting"]
    if start in ("wall_breach", "overspeed") and problem.ng:
        assert ref.slack > 1e-3  # the exact penalty is exercised
    if start == "open" and problem.ng:
        assert ref.slack < 1e-8
    winner = min(sols.values(), key=lambda sol: sol.objective)
    assert largest_local_descent(problem, x0, W, winner.u) >= -1e-7 * winner.objective


def test_ipopt_nlp_is_the_reference_at_any_inputs(problem: ScenarioProblem, solvers: dict) -> None:
    """The NLPs read the force in the layout of ``check_data`` (``(Ns, N, nw)``)."""
    rng = np.random.default_rng(5)
    x0 = STARTS["towards_wall"] + rng.normal(0.0, 0.05, size=(NS, 4))
    W = sample_forces(problem.model, 7)
    u = rng.uniform(problem.input_lower, problem.input_upper, size=(N, problem.nu))
    X = problem.rollout(x0, W, u)
    for name in ("ipopt", "ipopt_multiple_shooting"):
        solver = solvers[name]
        nlp = solver._nlp.nlp
        z = [u.ravel(), problem.minimal_slack(X).ravel()]
        if name == "ipopt_multiple_shooting":
            z.append(X[:, 1:].transpose(1, 0, 2).ravel())
        fg = ca.Function("fg", [nlp["x"], nlp["p"]], [nlp["f"], nlp["g"]])
        no_backoff = np.zeros(problem.ng * problem.horizon)
        f, g = fg(np.concatenate(z), np.concatenate([x0.ravel(), W.ravel(), no_backoff]))
        g = g.full().ravel()
        assert float(f) == pytest.approx(problem.objective(x0, W, u), rel=1e-12)
        n_dyn = problem.nx * N * NS if name == "ipopt_multiple_shooting" else 0
        assert g.size == n_dyn + problem.ng * N * NS
        np.testing.assert_allclose(g[:n_dyn], 0.0, atol=1e-12)  # the states are the rollout
        if problem.ng:
            assert np.sum(problem.minimal_slack(X)) > 0.0  # an active penalty term was checked
            assert np.max(g[n_dyn:]) == pytest.approx(0.0, abs=1e-12)


def test_per_scenario_initial_states(problem: ScenarioProblem, solvers: dict) -> None:
    rng = np.random.default_rng(3)
    x0 = STARTS["towards_wall"] + rng.normal(0.0, 0.05, size=(NS, 4))
    W = sample_forces(problem.model, 3)
    objectives = []
    for name in ("fast", "ipopt", "ipopt_multiple_shooting"):
        solvers[name].reset()
        sol = solvers[name].solve(x0, W)
        assert sol.success, (name, sol.status)
        np.testing.assert_allclose(sol.predicted[:, 0], x0)
        objectives.append(sol.objective)
    assert max(objectives) == pytest.approx(min(objectives), rel=1e-6)


# ----------------------------------------------------------------------------- env and filter


MEASUREMENT_STD = np.array([0.1, 0.1, 0.1, 0.1])  # [m, m, m/s, m/s]
START = np.array([0.0, 0.0, 0.5, 0.0])


def make_env(
    system: ControlSystem, max_steps: int = 80, latent_start: str = "stationary"
) -> LatentForceEnv:
    return LatentForceEnv(
        point_mass_model(system),
        COST,
        START,
        MEASUREMENT_STD,
        max_steps=max_steps,
        latent_start=latent_start,
    )


def feedback(y: np.ndarray) -> np.ndarray:
    """A PD law towards (2, 0.6) m, clipped into the input bounds."""
    target = np.array([2.0, 0.6])
    a = 1.5 * (target - y[:2]) - 2.0 * y[2:]
    return np.clip(a, -ACCEL_MAX, ACCEL_MAX)


def test_particle_filter_tracks_the_state_and_the_hidden_force() -> None:
    system = point_mass()
    env = make_env(system)
    model = env.model
    rng = np.random.default_rng(11)
    y, info = env.reset(seed=4)
    n = 3000
    factor = psd_factor(model.stationary_latent_covariance())
    prior = np.hstack(
        [
            y + rng.standard_normal((n, 4)) * MEASUREMENT_STD,
            rng.standard_normal((n, model.latent_dim)) @ factor.T,
        ]
    )
    pf = ParticleFilter(
        model.transition, gaussian_log_likelihood(MEASUREMENT_STD, np.arange(4)), prior, rng
    )
    state_err, meas_err, force_err, force = [], [], [], []
    u = feedback(pf.mean[:4])
    for k in range(80):
        y, _, terminated, truncated, info = env.step(u)
        pf.step(u, y)
        x_hat = pf.mean
        if k >= 20:  # past the start-up transient of the force estimate
            state_err.append(x_hat[:4] - info["true_state"])
            meas_err.append(y - info["true_state"])
            # Both latent states are those of the step about to be taken (info's
            # latent_state, the filter's prediction): the force is never measured.
            force_err.append(
                model.latent_force(x_hat[4:]) - model.latent_force(info["latent_state"])
            )
            force.append(model.latent_force(info["latent_state"]))
        u = feedback(x_hat[:4])
        assert not terminated
    state_rms = np.sqrt(np.mean(np.square(state_err), axis=0))
    meas_rms = np.sqrt(np.mean(np.square(meas_err), axis=0))
    # Filtering beats the raw measurement on every state, and by far on average (the
    # positions integrate the velocities; a filter that lost track would be off by more
    # than the measurement noise).
    assert np.all(meas_rms > 0.8 * MEASUREMENT_STD)  # the measurements were noisy
    assert np.all(state_rms < 0.9 * MEASUREMENT_STD), state_rms
    assert np.mean(state_rms / MEASUREMENT_STD) < 0.6, state_rms
    # The force is never measured; the filter infers it from the velocities.
    force_rms = np.sqrt(np.mean(np.square(force_err), axis=0))
    assert np.all(force_rms < 0.5 * FORCE_STD), force_rms
    assert np.all(np.std(force, axis=0) > 0.2 * FORCE_STD)  # the force did vary


@pytest.mark.parametrize("variant", sorted(VARIANTS))
def test_env_episode_with_the_scenario_mpc(variant: str) -> None:
    system = point_mass(**VARIANTS[variant])
    # The force starts at rest: the scenario MPC below draws it from the prior, with no
    # filter to learn a strong persistent push, which short horizons cannot anticipate.
    env = TimeLimit(make_env(system, latent_start="zero"), 30)
    model = env.unwrapped.model
    problem = ScenarioProblem(model, COST, horizon=N, n_scenarios=NS, slack_penalty=1.0e3)
    solver = make_solver(problem, "fast", max_iter=50)
    rng = np.random.default_rng(2)
    factor = psd_factor(model.stationary_latent_covariance())
    y, info = env.reset(seed=1)
    assert set(info) >= {f"{name}_excess" for name in system.constraint_labels}
    assert info["constraint_excess"].shape == (system.ng,)
    x = info["true_state"]
    wall = []
    for _ in range(30):
        # Scenario forces drawn from the prior (no filter here: the test is the env loop).
        z0 = rng.standard_normal((NS, model.latent_dim)) @ factor.T
        sol = solver.solve(y, model.sample_latent_forecasts(z0, N, rng))
        assert sol.success, sol.status
        y, reward, terminated, truncated, info = env.step(sol.u[0])
        assert reward == pytest.approx(-COST.stage_cost(x, sol.u[0]), rel=1e-12)
        x = info["true_state"]
        assert info["latent_force"] is not None
        if system.nw == 1:
            assert isinstance(info["latent_force"], float)
        else:
            assert info["latent_force"].shape == (2,)
        excess = system.constraint_excess(x)
        np.testing.assert_array_equal(info["constraint_excess"], excess)
        for j, name in enumerate(system.constraint_labels):
            assert info[f"{name}_excess"] == excess[j]
        wall.append(x[1])
        if terminated or truncated:
            break
    assert truncated and not terminated
    goal = COST.x_goal[:2]
    assert np.linalg.norm(x[:2] - goal) < 0.7 * np.linalg.norm(START[:2] - goal)
    if system.ng:
        # The goal lies 0.3 m beyond the wall: the MPC heads for it and stops at the wall
        # (short of it when the force also pushes along y), not through it.
        assert WALL - 0.5 < max(wall) < WALL + 0.05
        assert info["speed_excess"] == 0.0
    else:
        assert max(wall) > WALL + 0.1  # nothing holds it back
