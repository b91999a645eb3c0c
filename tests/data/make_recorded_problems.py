"""Regenerate ``recorded_problems.npz``: scenario problems met in closed-loop paper episodes.

Run from the repository root: ``.venv/bin/python tests/data/make_recorded_problems.py``.

The scenario agent (fast solver) drives paper-config episodes for env seeds 0..5 (the
benchmark's recorder, at most 120 steps each). The problems are replayed through a fresh
fast solver in closed-loop order, which gives the warm start each one met. Kept, by a
fixed rule: for every seed the problem at step 25 and the last one (near the goal), plus,
on seeds whose problems need slack, the first such problem and every 10th step after it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from controllers.problem import minimal_slack, rollout
from controllers.solvers.fast import FastScenarioSolver
from experiments import benchmark

SEEDS = range(6)
OUT = Path(__file__).with_name("recorded_problems.npz")


def main() -> None:
    problems = benchmark.record_problems(benchmark.DEFAULT_CONFIG, seeds=SEEDS, max_steps=120)
    problem = benchmark.problem_from_config(benchmark.DEFAULT_CONFIG, n_scenarios=150)
    solver = FastScenarioSolver(problem)
    rows, previous_seed = [], None
    for seed, step, x0, W in problems:
        if seed != previous_seed:
            solver.reset()
            previous_seed = seed
        n = problem.horizon
        guess = np.zeros((n, 2)) if solver._prev_u is None else solver._prev_u[[*range(1, n), -1]]
        sol = solver.solve(x0, W)
        slack = float(np.sum(minimal_slack(problem, rollout(problem, x0, W, sol.u))))
        rows.append((seed, step, x0, W, guess, slack))
    keep = []
    for seed in SEEDS:
        mine = [r for r in rows if r[0] == seed]
        chosen = {25, mine[-1][1]}
        slack_steps = [r[1] for r in mine if r[5] > 1e-6]
        if slack_steps:
            chosen |= {s for s in slack_steps if (s - slack_steps[0]) % 10 == 0}
        keep += [r for r in mine if r[1] in chosen]
    np.savez_compressed(
        OUT,
        seed=np.array([r[0] for r in keep]),
        step=np.array([r[1] for r in keep]),
        x0=np.stack([np.asarray(r[2], dtype=float) for r in keep]),
        W=np.stack([r[3] for r in keep]),
        u_guess=np.stack([r[4] for r in keep]),
        slack=np.array([r[5] for r in keep]),
    )
    print(f"{len(keep)} problems -> {OUT}")
    for r in keep:
        print(f"  seed {r[0]} step {r[1]:3d} slack {r[5]:.3g}")


if __name__ == "__main__":
    main()
