"""The chance constraint against its design (``experiments.report.chance``): the design's
epsilon, the offline draws against a violation probability known in closed form, the
closed-loop estimate's intervals on a simulated process, and the offline draws aligned with
recorded episodes."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from controllers.config import load_config
from controllers.scenario_count import campi_garatti_scenarios
from experiments.evaluation import evaluate
from experiments.report.chance import (
    DEFAULT_CONFIDENCE,
    agent_design,
    chance_check,
    closed_loop_first_step,
    design_epsilon,
    plan_violations,
)
from experiments.report.results import load_results, load_trajectory
from experiments.report.stats import pooled_ratio_ci
from lfm_env import gp
from lfm_env.model import LatentForceModel
from lfm_env.system import ControlSystem
from lfm_env.xp import xp


@pytest.mark.parametrize("ns, d, beta", [(150, 14, 1e-3), (50, 20, 0.05), (400, 7, 1e-6)])
def test_design_epsilon_is_the_level_the_scenario_count_meets(ns, d, beta):
    eps = design_epsilon(ns, d, beta)
    assert campi_garatti_scenarios(eps * (1 + 1e-9), beta, d) <= ns
    assert campi_garatti_scenarios(eps * (1 - 1e-6), beta, d) > ns
    assert design_epsilon(d - 1, d, beta) == 1.0  # fewer scenarios than decisions: none


def test_the_agents_designs_under_the_paper_config():
    cfg = load_config("configs/paper.yaml")
    scenario = agent_design("scenario", cfg)
    assert (scenario.n_scenarios, scenario.n_decision) == (150, 14)
    assert scenario.beta == DEFAULT_CONFIDENCE and scenario.source == "default beta"
    assert scenario.epsilon == pytest.approx(design_epsilon(150, 14, DEFAULT_CONFIDENCE))
    assert scenario.mean_bound == pytest.approx(14 / 151)
    for agent in ("pf", "nominal", "oracle", "robust", "dompc", "mine"):  # robust: forecast mean
        assert agent_design(agent, cfg).n_scenarios is None
    raw = cfg.to_dict()
    raw["agents"].update(n_scenarios=None, violation_level=0.2, confidence=1e-4)
    designed = agent_design("scenario_particles", load_config(raw))
    assert (designed.epsilon, designed.beta) == (0.2, 1e-4)
    assert designed.n_scenarios == campi_garatti_scenarios(0.2, 1e-4, 14)
    raw["agents"]["robust"] = {"forecast": "sampled", "n_scenarios": 40}
    robust = agent_design("robust", load_config(raw))
    assert robust.n_scenarios == 40 and robust.epsilon == design_epsilon(40, 14, 1e-4)


# --------------------------------------------------------------------------- a known law

DT, LIMIT, PROCESS_STD = 0.1, 0.55, 0.04


def _line() -> LatentForceModel:
    """``dp/dt = u + w`` with ``p <= LIMIT``: the position is Gaussian at every step."""

    def rhs(x, u, w):
        ((speed,), (force,)) = xp.unstack(u), xp.unstack(w)
        return xp.stack([speed + force])

    def limit(x):
        (p,) = xp.unstack(x)
        return xp.stack([p - LIMIT])

    system = ControlSystem(
        name="line",
        state_names=("p [m]",),
        input_names=("u [m/s]",),
        rhs=rhs,
        input_lower=[-5.0],
        input_upper=[5.0],
        constraints=limit,
        constraint_names=("limit [m]",),
        force_names=("w [m/s]",),
    )
    return LatentForceModel(
        system, kernel=gp.matern(1.5, 1.0, 0.5), dt=DT, process_noise_std=[PROCESS_STD]
    )


def _exact(model: LatentForceModel, p0: float, z0: np.ndarray, plan: np.ndarray) -> np.ndarray:
    """``P(p_k > LIMIT)``, ``k = 1..N``: ``p_k = p0 + dt sum_{i<k} (u_i + H z_i) + noise``
    with ``z_i = A^i z0 + sum_{l<i} A^(i-1-l) eta_l``, ``eta ~ N(0, Q)``."""
    A, H, Q = model.A, model.H, model.Q
    N = len(plan)
    out = []
    for k in range(1, N + 1):
        mean = p0 + DT * sum(
            plan[i, 0] + (H @ np.linalg.matrix_power(A, i) @ z0)[0] for i in range(k)
        )
        var = k * PROCESS_STD**2
        for ell in range(k - 1):  # eta_ell enters z_i for i = ell+1 .. k-1
            c = DT * sum(H @ np.linalg.matrix_power(A, i - 1 - ell) for i in range(ell + 1, k))
            var += (c @ Q @ c.T).item()
        out.append(stats.norm.sf((LIMIT - mean) / math.sqrt(var)))
    return np.array(out)


def test_offline_draws_recover_a_violation_probability_known_in_closed_form():
    model = _line()
    z0 = np.array([0.4, -0.8])  # the force 0.4 m/s, falling
    plan = np.array([[0.1], [-0.2], [-0.4], [-0.5], [-0.6], [-0.7]])  # backing off the limit
    exact = _exact(model, 0.45, z0, plan)
    assert np.all((exact > 0.1) & (exact < 0.3))  # 0.106 .. 0.281: worth estimating
    episodes, steps = 30, 4  # the same plan from the same truth, as recorded episodes
    T = episodes * steps
    per_group, joint = plan_violations(
        model,
        np.broadcast_to(plan, (T, *plan.shape)),
        np.full((T, 1), 0.45),
        np.broadcast_to(z0, (T, 2)),
        n_draws=100,
        rng=np.random.default_rng(1),
    )
    sums = per_group[:, :, 0].reshape(episodes, steps, -1).sum(axis=1)
    for k, p in enumerate(exact):
        e = pooled_ratio_ci(sums[:, k], np.full(episodes, steps))
        assert e.low <= p <= e.high, (k + 1, p, e)
        assert abs(e.mean - p) < 4 * math.sqrt(p * (1 - p) / (T * 100))  # 4 standard errors
    # The joint event grows with k and is at least every step's own event.
    assert np.all(np.diff(joint, axis=1) >= 0) and np.all(joint >= per_group[:, :, 0])


def test_the_closed_loop_estimate_covers_a_known_probability_as_its_level_says():
    """Episodes of correlated steps (each episode has its own rate, mean ``p``): the 95%
    interval of the pooled per-step probability holds ``p`` in about 95% of replications,
    and never holds a probability twice as large."""
    rng = np.random.default_rng(7)
    p, episodes, steps, replications = 0.12, 40, 50, 300
    covered = 0
    for _ in range(replications):
        rates = rng.beta(2.0, 2.0 * (1 - p) / p, size=episodes)  # mean p
        counts = rng.binomial(steps, rates)
        rows = [{"steps": steps, "track_violation_steps": c} for c in counts]
        e = closed_loop_first_step(rows, "track")
        covered += e.low <= p <= e.high
        assert not e.low <= 2 * p <= e.high
    assert 0.90 <= covered / replications <= 0.99


# --------------------------------------------------------------------------- recorded episodes


def test_offline_draws_are_aligned_with_the_recorded_episodes(tmp_path):
    """Without process noise, step 1 of the offline draws is the env's next true state: each
    applied plan's k = 1 fraction is exactly whether the recorded step violated the group."""
    config = {
        "env": {"max_steps": 25, "process_noise_diffusion": [0.0, 0.0, 0.0, 0.0]},
        "agents": {"horizon": 5, "n_scenarios": 10, "n_particles": 300},
    }
    out = tmp_path / "run"
    evaluate(["pf", "scenario"], [0, 1], config, out=out, progress=False)
    results = load_results(out)
    truth = results.config.make_model()
    checked = 0
    for agent in ("pf", "scenario"):
        for seed in (0, 1):
            traj = load_trajectory(results, agent, seed)
            ok = np.flatnonzero(traj["fallback"] == "")
            per_group, _ = plan_violations(
                truth,
                traj["plan"][ok],
                traj["true_state"][ok],
                traj["latent_state"][ok],
                n_draws=3,
                rng=np.random.default_rng(0),
            )
            for j, g in enumerate(results.system.constraint_groups):
                recorded = (traj[f"{g}_excess"][ok] > 0).astype(float)
                np.testing.assert_array_equal(per_group[:, 0, j], recorded)
                checked += int(recorded.sum())
    assert checked > 0  # some recorded violations were reproduced
    cals = {c.agent: c for c in chance_check(results, n_draws=20)}
    scenario = cals["scenario"]
    assert scenario.design.n_scenarios == 10 and cals["pf"].design.n_scenarios is None
    assert scenario.offline_steps == scenario.steps  # every plan of this run was applied
    for j in range(len(scenario.groups)):
        # With no process noise the closed loop is the offline step 1, draw for draw.
        assert scenario.offline[j][0].mean == pytest.approx(scenario.closed_loop[j].mean)
