"""Regenerate ``feedback_problems.npz``: feedback scenario problems met in closed loop, with
their feedback laws and reference solutions.

Run from the repository root: ``.venv/bin/python tests/data/make_feedback_problems.py``.

Three sets (:data:`SETS`), each recorded from the closed loop of an open-loop agent (its own
seed the env seed): the problem the agent met at the listed steps of the listed seeds
(``last_info["x0"]``, ``["W"]``, broadcast to one initial state per scenario):

* ``paper_n7``: the paper's config and agent (``scenario``, N = 7, Ns = 150); seed 4 meets a
  latent force beyond full throttle (slack);
* ``paper_n15``: the same at N = 15;
* ``quadrotor``: the quadrotor config with ``scenario_particles`` (N = 10, Ns = 50): every
  scenario starts from its own particle, so the shared first input and ``K_0 = 0`` matter.

For each problem the law is :func:`controllers.feedback_law.feedback_law` along the open-loop
plan of the fast solver (cold, from zero inputs): the agent's first-step rule. ``u_guess``
is that plan (the decision's warm start). The reference is the textbook IPOPT formulation
(``ipopt_multiple_shooting``, ``tol`` = :data:`REFERENCE_TOL`) on the feedback problem with
that law, started from ``u_guess``: ``reference_u`` and its
:meth:`~controllers.problem.ScenarioProblem.objective` with the law
(``reference_objective``).

Arrays, per set ``S``: ``S_seed``, ``S_step`` ``(n,)``; ``S_x0`` ``(n, Ns, nx)``; ``S_W``
``(n, Ns, N, nw)``; ``S_K`` ``(n, N, nu, nx)``; ``S_r`` ``(n, N, nx)``; ``S_u_guess``,
``S_reference_u`` ``(n, N, nu)``; ``S_reference_objective``, ``S_slack`` (of the reference)
``(n,)``; and ``sets`` (the names), ``S_config`` (the preset), ``S_horizon``,
``S_n_scenarios``.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import gymnasium as gym
import numpy as np

import lfm_env  # noqa: F401  (registers the env ids)
from controllers.agents import make_agent
from controllers.config import load_config
from controllers.feedback_law import feedback_law
from controllers.solvers import make_solver

ROOT = Path(__file__).resolve().parents[2]
OUT = Path(__file__).with_name("feedback_problems.npz")
REFERENCE_TOL = 1e-10  # IPOPT tolerance of the reference solutions
#: name -> (preset, agent, horizon, {seed: steps})
SETS: dict[str, tuple[str, str, int, dict[int, tuple[int, ...]]]] = {
    "paper_n7": ("paper", "scenario", 7, {0: (25,), 4: (10, 30)}),
    "paper_n15": ("paper", "scenario", 15, {0: (10,), 4: (10,)}),
    "quadrotor": ("quadrotor", "scenario_particles", 10, {0: (5, 20), 1: (40,)}),
}


def config_of(preset: str, horizon: int):
    cfg = load_config(ROOT / "configs" / f"{preset}.yaml")
    agents = dataclasses.replace(cfg.agents, horizon=horizon)
    return dataclasses.replace(cfg, agents=agents)


def record(cfg, agent_name: str, seed: int, steps: tuple[int, ...]) -> list[tuple]:
    """``(seed, step, x0, W)`` the agent met at ``steps`` of the episode of ``seed``."""
    env = gym.make(cfg.env_id, config=cfg.env)
    out = []
    try:
        obs, _ = env.reset(seed=seed)
        agent = make_agent(agent_name, cfg)
        agent.reset(seed=seed)
        for step in range(max(steps) + 1):
            action = agent.act(obs)
            if step in steps:
                info = agent.last_info
                out.append((seed, step, np.array(info["x0"]), np.array(info["W"])))
            obs, _, terminated, truncated, _ = env.step(action)
            if terminated or truncated:
                raise RuntimeError(f"seed {seed} ended before step {max(steps)}")
    finally:
        env.close()
    return out


def make_set(name: str) -> dict[str, np.ndarray]:
    preset, agent_name, horizon, chosen = SETS[name]
    cfg = config_of(preset, horizon)
    problem = cfg.make_problem()
    feedback = cfg.make_problem(prediction="feedback")
    open_loop = make_solver(problem, "fast")
    reference = make_solver(
        feedback, "ipopt_multiple_shooting", ipopt_options={"tol": REFERENCE_TOL}
    )
    rows = []
    for seed, steps in chosen.items():
        for seed_, step, x0, W in record(cfg, agent_name, seed, steps):
            x0, W = problem.check_data(x0, W)
            open_loop.reset()
            plan = open_loop.solve(x0, W).u
            law = feedback_law(feedback, x0, W, plan)
            reference.reset()
            sol = reference.solve(x0, W, u_guess=plan, law=law)
            if not sol.success:
                raise RuntimeError(f"{name} seed {seed_} step {step}: reference {sol.status}")
            objective = feedback.objective(x0, W, sol.u, law=law)
            rows.append((seed_, step, x0, W, law, plan, sol.u, objective, sol.slack))
            print(
                f"  {name} seed {seed_} step {step:3d}: reference objective {objective:.8g}, "
                f"slack {sol.slack:.3g}, {sol.iterations} IPOPT iterations"
            )
    out = {
        "seed": np.array([r[0] for r in rows]),
        "step": np.array([r[1] for r in rows]),
        "x0": np.stack([r[2] for r in rows]),
        "W": np.stack([r[3] for r in rows]),
        "K": np.stack([r[4].K for r in rows]),
        "r": np.stack([r[4].r for r in rows]),
        "u_guess": np.stack([r[5] for r in rows]),
        "reference_u": np.stack([r[6] for r in rows]),
        "reference_objective": np.array([r[7] for r in rows]),
        "slack": np.array([r[8] for r in rows]),
        "config": np.array(preset),
        "horizon": np.array(horizon),
        "n_scenarios": np.array(problem.n_scenarios),
    }
    return {f"{name}_{k}": v for k, v in out.items()}


def main() -> None:
    data: dict[str, np.ndarray] = {"sets": np.array(list(SETS))}
    for name in SETS:
        data.update(make_set(name))
    np.savez_compressed(OUT, **data)
    print(f"-> {OUT}")


if __name__ == "__main__":
    main()
