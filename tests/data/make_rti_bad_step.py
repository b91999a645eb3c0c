"""Regenerate ``rti_bad_step.npz``: a scenario problem on which one real-time iteration from
the plan it starts at makes the plan's slack grow (the agent's RTI fallback must notice it).

Run from the repository root: ``.venv/bin/python tests/data/make_rti_bad_step.py``.

The paper's problem at ``N = 15`` with ``Ns = 20`` scenarios drawn from the latent-force
prior (scaled), the car at random states, and a random warm start whose last two inputs are
equal (so it is the previous plan ``prev`` shifted by one step, ``prev = [u_0, u_0 .. u_{N-2}]``
shifted gives ``u``): the first of generator seed 0's draws where one SQP iteration of the
compiled loop (``iterations=1``) ends with more slack than it started with is kept.

Arrays: ``x0`` ``(nx,)``, ``W`` ``(Ns, N)``, ``u`` ``(N, nu)`` (the shifted plan), ``prev``
``(N, nu)``; ``horizon``, ``n_scenarios``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from controllers.config import load_config
from controllers.solvers import make_solver

OUT = Path(__file__).with_name("rti_bad_step.npz")
N, NS = 15, 20


def main() -> None:
    problem = load_config("paper").make_problem(horizon=N, n_scenarios=NS)
    model = problem.model
    solver = make_solver(problem, "fast_c", restarts=())
    rng = np.random.default_rng(0)
    for _ in range(2000):
        x0 = rng.uniform([0.0, -1.5, 1.0, -0.8], [60.0, 1.5, 10.0, 0.8])
        z0 = np.zeros((NS, model.latent_dim))
        W = model.sample_latent_forecasts(z0, N, rng) * rng.uniform(0.5, 3.0)
        u = rng.uniform(problem.input_lower, problem.input_upper, (N, problem.nu))
        u *= rng.uniform(0.0, 1.0)
        u[-1] = u[-2]
        sol = solver.solve(x0, W, u_guess=u, iterations=1)
        if sol.usable and sol.slack > sol.extra["start_slack"] + 1e-3:
            prev = np.concatenate([u[:1], u[:-1]])
            np.savez(OUT, x0=x0, W=W, u=u, prev=prev, horizon=N, n_scenarios=NS)
            print(f"{OUT}: slack {sol.extra['start_slack']:.6g} -> {sol.slack:.6g}")
            return
    raise SystemExit("no such problem among the draws")


if __name__ == "__main__":
    main()
