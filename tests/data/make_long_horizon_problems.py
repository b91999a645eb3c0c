"""Regenerate ``long_horizon_problems.npz``: closed-loop-like scenario problems at N = 15, 30.

Run from the repository root: ``.venv/bin/python tests/data/make_long_horizon_problems.py``.

The scenario agent (fast solver, paper config, N = 7) drives paper episodes for env seeds
0..5 (at most :data:`MAX_STEPS` steps each) and its estimates are recorded
(:func:`experiments.benchmark.problems.record_closed_loop`). At the fixed (horizon, seed, step)
points of :data:`CHOSEN`, ``Ns`` = :data:`N_SCENARIOS` latent-force scenarios of the longer
horizon are drawn around that estimate as the agent draws them
(:func:`experiments.benchmark.problems.scenario_draws`, one generator per horizon seeded with
:data:`DRAW_SEED` and the horizon). The points were chosen where the SQP used to need many
iterations (mid-manoeuvre and near the goal, where the plan brakes hard and turns). The
warm start ``u_guess`` is the solver's own first guess (zeros clipped into the bounds).
The reference is IPOPT on the condensed NLP (``tol`` = :data:`REFERENCE_TOL`) started from
``u_guess``: ``reference_u`` and its objective ``reference_objective``.

Arrays per horizon ``N`` (suffix ``_N``): ``seed``, ``step`` ``(n,)``; ``x0`` ``(n, nx)``;
``W`` ``(n, Ns, N, nw)``; ``u_guess``, ``reference_u`` ``(n, N, nu)``;
``reference_objective`` ``(n,)``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from controllers.solvers import make_solver
from experiments.benchmark import problems as benchmark_problems

SEEDS = range(6)
MAX_STEPS = 45
N_SCENARIOS = 50
DRAW_SEED = 16
REFERENCE_TOL = 1e-10  # IPOPT tolerance of the reference solutions
CHOSEN = {15: [(2, 30), (2, 40), (0, 40)], 30: [(0, 0), (2, 40), (4, 20)]}
OUT = Path(__file__).with_name("long_horizon_problems.npz")


def main() -> None:
    cfg = benchmark_problems.experiment_config(benchmark_problems.DEFAULT_CONFIG)
    _, anchors = benchmark_problems.record_closed_loop(cfg, seeds=SEEDS, max_steps=MAX_STEPS)
    by_key = {(a.seed, a.step): a for a in anchors}
    out: dict[str, np.ndarray] = {}
    for n, points in CHOSEN.items():
        problem = cfg.make_problem(n_scenarios=N_SCENARIOS, horizon=n)
        rng = np.random.default_rng([DRAW_SEED, n])
        drawn = benchmark_problems.scenario_draws(problem, [by_key[k] for k in points], rng)
        ipopt = make_solver(problem, "ipopt", ipopt_options={"tol": REFERENCE_TOL})
        guess = np.clip(np.zeros((n, problem.nu)), problem.input_lower, problem.input_upper)
        rows = []
        for p in drawn:
            sol = ipopt.solve(p.x0, p.W, u_guess=guess)
            objective = problem.objective(p.x0, p.W, sol.u)
            print(f"N={n} seed {p.seed} step {p.step}: {sol.status}, objective {objective:.10g}")
            rows.append((p, sol.u, objective))
        out[f"seed_{n}"] = np.array([p.seed for p, _, _ in rows])
        out[f"step_{n}"] = np.array([p.step for p, _, _ in rows])
        out[f"x0_{n}"] = np.stack([np.asarray(p.x0, dtype=float) for p, _, _ in rows])
        out[f"W_{n}"] = np.stack([problem.check_data(p.x0, p.W)[1] for p, _, _ in rows])
        out[f"u_guess_{n}"] = np.stack([guess for _ in rows])
        out[f"reference_u_{n}"] = np.stack([u for _, u, _ in rows])
        out[f"reference_objective_{n}"] = np.array([obj for _, _, obj in rows])
    np.savez_compressed(OUT, **out)
    print(f"wrote {OUT} ({OUT.stat().st_size / 1e3:.0f} kB)")


if __name__ == "__main__":
    main()
