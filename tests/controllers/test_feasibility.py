"""The least slack of the shared linear constraints: a lower bound that no input beats."""

from __future__ import annotations

import numpy as np
import pytest

from controllers.feasibility import SharedConstraints, shared_slack_bound
from controllers.problem import ScenarioProblem
from lfm_env.worlds.sine_track.config import SineTrackConfig

N = 10
SPEED = 2  # the bicycle's speed state


def _problem(n_scenarios: int) -> ScenarioProblem:
    config = SineTrackConfig()
    return ScenarioProblem(
        config.make_model(), config.make_cost(), horizon=N, n_scenarios=n_scenarios
    )


def _shared_slack(problem: ScenarioProblem, shared, x0, W, u) -> float:
    X = problem.rollout(x0, W, u)
    return float(problem.minimal_slack(X)[:, shared.indices].sum())


def test_two_scenarios_spreading_wider_than_the_speed_band() -> None:
    """Forces +F and -F from v0 = 4 m/s (the middle of the band [0, 8]): at step k the
    speeds differ by 2 dt k F whatever the inputs, so each step's two speed slacks sum to
    at least 2 dt k F - 8, and with zero acceleration exactly that."""
    problem = _problem(2)
    F, dt = 30.0, problem.dt
    x0 = np.zeros((2, problem.nx))
    x0[:, SPEED] = 4.0
    W = np.zeros((2, N, 1))
    W[0], W[1] = F, -F
    spread = 2.0 * dt * F * np.arange(1, N + 1)  # (Euler: the force acts from step 1 on)
    expected = float(np.maximum(spread - 8.0, 0.0).sum())
    assert expected > 10.0
    bound = shared_slack_bound(problem, x0, W)
    assert bound.infeasible
    assert bound.total == pytest.approx(expected, rel=1e-9)
    labels = [problem.system.constraint_labels[j] for j in bound.constraints]
    assert labels == ["speed_min", "speed_max"]


@pytest.mark.parametrize("seed", range(3))
def test_no_input_has_less_slack_and_the_bound_is_attained(seed: int) -> None:
    rng = np.random.default_rng(seed)
    problem = _problem(20)
    shared = SharedConstraints.of(problem)
    x0 = np.zeros((20, problem.nx))
    x0[:, SPEED] = rng.uniform(0.5, 7.5, size=20)
    W = rng.normal(scale=15.0, size=(20, N, 1))  # strong: some steps infeasible
    bound = shared_slack_bound(problem, x0, W, shared=shared)
    assert bound.total > 0.0
    lower, upper = problem.input_lower, problem.input_upper
    for _ in range(50):
        u = rng.uniform(lower, upper, size=(N, problem.nu))
        assert _shared_slack(problem, shared, x0, W, u) >= bound.total - 1e-9
    # its own input sequence attains it (within the inputs' bounds)
    assert np.all(bound.u >= lower - 1e-12) and np.all(bound.u <= upper + 1e-12)
    attained = _shared_slack(problem, shared, x0, W, bound.u)
    assert attained == pytest.approx(bound.total, rel=1e-7, abs=1e-7)
    np.testing.assert_allclose(bound.slack.sum(), bound.total)


def test_a_mild_problem_is_not_declared_infeasible() -> None:
    rng = np.random.default_rng(0)
    problem = _problem(50)
    x0 = np.zeros((50, problem.nx))
    x0[:, SPEED] = 3.0
    W = rng.normal(scale=0.3, size=(50, N, 1))
    bound = shared_slack_bound(problem, x0, W)
    assert not bound.infeasible and bound.total <= 1e-9


def test_backoff_tightens_the_band() -> None:
    """A back-off of 1 m/s on both speed bounds narrows the band to 6 m/s: a spread of
    7 m/s that fit before now needs 1 m/s of slack at that step."""
    problem = _problem(2)
    x0 = np.zeros((2, problem.nx))
    x0[:, SPEED] = [0.5, 7.5]
    W = np.zeros((2, N, 1))
    assert not shared_slack_bound(problem, x0, W).infeasible
    backoff = np.zeros((N, problem.ng))
    speed = [problem.system.constraint_labels.index(n) for n in ("speed_min", "speed_max")]
    backoff[:, speed] = 1.0
    bound = shared_slack_bound(problem, x0, W, backoff=backoff)
    assert bound.total == pytest.approx(N * 1.0, rel=1e-9)
