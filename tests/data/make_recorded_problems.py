"""Regenerate ``recorded_problems.npz``: scenario problems met in closed-loop paper episodes,
with reference solutions.

Run from the repository root: ``.venv/bin/python tests/data/make_recorded_problems.py``
(``--keep-problems`` keeps the recorded problems of the existing file and recomputes only
the reference solutions).

The scenario agent (fast solver) drives paper-config episodes for env seeds 0..5 (the
benchmark's recorder, at most 120 steps each). The problems are replayed through a fresh
fast solver in closed-loop order, which gives the warm start each one met (``u_guess``)
and whether it needs slack. Kept, by a fixed rule: for every seed the problem at step 25
and the last one (near the goal), plus, on seeds whose problems need slack, the first such
problem and every 10th step after it. The reference of each kept problem is the textbook
IPOPT formulation (``ipopt_multiple_shooting``, ``tol`` = :data:`REFERENCE_TOL`) started
from ``u_guess``: ``reference_u`` and its objective
:meth:`~controllers.problem.ScenarioProblem.objective` (``reference_objective``).

Arrays: ``seed``, ``step`` ``(n,)``; ``x0`` ``(n, nx)``; ``W`` ``(n, Ns, N, nw)``;
``u_guess``, ``reference_u`` ``(n, N, nu)``; ``slack`` (of the fast solver's plan),
``reference_objective`` ``(n,)``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from controllers.solvers import make_solver
from experiments.benchmark import problems as benchmark_problems

SEEDS = range(6)
MAX_STEPS = 120
N_SCENARIOS = 150
REFERENCE_TOL = 1e-10  # IPOPT tolerance of the reference solutions
OUT = Path(__file__).with_name("recorded_problems.npz")


def record(problem) -> dict[str, np.ndarray]:
    """Record the episodes and keep problems by the rule of the module docstring."""
    problems = benchmark_problems.record_problems(
        benchmark_problems.DEFAULT_CONFIG, seeds=SEEDS, max_steps=MAX_STEPS
    )
    solver = make_solver(problem, "fast")
    rows, previous_seed, previous_u = [], None, None
    n = problem.horizon
    for seed, step, x0, W in problems:
        if seed != previous_seed:
            solver.reset()
            previous_seed, previous_u = seed, None
        # The solver's own default guess: the previous plan shifted, zeros (clipped) first.
        if previous_u is None:
            guess = np.clip(np.zeros((n, problem.nu)), problem.input_lower, problem.input_upper)
        else:
            guess = previous_u[[*range(1, n), -1]]
        sol = solver.solve(x0, W)
        previous_u = sol.u
        slack = float(np.sum(problem.minimal_slack(problem.rollout(x0, W, sol.u))))
        rows.append((seed, step, x0, W, guess, slack))
    keep = []
    for seed in SEEDS:
        mine = [r for r in rows if r[0] == seed]
        chosen = {25, mine[-1][1]}
        slack_steps = [r[1] for r in mine if r[5] > 1e-6]
        if slack_steps:
            chosen |= {s for s in slack_steps if (s - slack_steps[0]) % 10 == 0}
        keep += [r for r in mine if r[1] in chosen]
    return {
        "seed": np.array([r[0] for r in keep]),
        "step": np.array([r[1] for r in keep]),
        "x0": np.stack([np.asarray(r[2], dtype=float) for r in keep]),
        "W": np.stack([problem.check_data(r[2], r[3])[1] for r in keep]),
        "u_guess": np.stack([r[4] for r in keep]),
        "slack": np.array([r[5] for r in keep]),
    }


def add_references(problem, data: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """``data`` with the textbook's solution of every problem, started from ``u_guess``."""
    textbook = make_solver(problem, "ipopt_multiple_shooting", ipopt_options={"tol": REFERENCE_TOL})
    us, objectives = [], []
    for x0, W, guess in zip(data["x0"], data["W"], data["u_guess"], strict=True):
        textbook.reset()
        sol = textbook.solve(x0, W, u_guess=guess)
        if not sol.success:
            raise RuntimeError(f"the reference solve failed: {sol.status}")
        us.append(sol.u)
        objectives.append(problem.objective(x0, W, sol.u))
    return {**data, "reference_u": np.stack(us), "reference_objective": np.array(objectives)}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--keep-problems",
        action="store_true",
        help="reuse the problems of the existing file; recompute only the references",
    )
    args = parser.parse_args(argv)
    problem = benchmark_problems.problem_from_config(n_scenarios=N_SCENARIOS)
    if args.keep_problems:
        with np.load(OUT) as old:
            data = {k: old[k] for k in ("seed", "step", "x0", "W", "u_guess", "slack")}
        pairs = zip(data["x0"], data["W"], strict=True)
        data["W"] = np.stack([problem.check_data(x0, W)[1] for x0, W in pairs])
    else:
        data = record(problem)
    data = add_references(problem, data)
    np.savez_compressed(OUT, **data)
    print(f"{len(data['seed'])} problems -> {OUT}")
    for i, (seed, step) in enumerate(zip(data["seed"], data["step"], strict=True)):
        print(
            f"  seed {seed} step {step:3d} slack {data['slack'][i]:.3g} "
            f"reference objective {data['reference_objective'][i]:.6g}"
        )


if __name__ == "__main__":
    main()
