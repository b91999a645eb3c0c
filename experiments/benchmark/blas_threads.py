"""A solve's time with and without ``OPENBLAS_NUM_THREADS`` exported, side by side: each case
in a fresh Python, the fast solver on ``tests/data/long_horizon_problems.npz``, the median
per problem printed with the BLAS thread count it ran with::

    python -m experiments.benchmark.blas_threads --horizon 30 --repeats 3 [--python OTHER]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]  # the checkout (tests/data)

CHILD = """
import json, sys, time
import numpy as np
from controllers.config import load_config
from controllers.solvers import make_solver
n = int(sys.argv[1])
d = np.load(sys.argv[2])
problem = load_config("paper").make_problem(n_scenarios=d[f"W_{n}"].shape[1], horizon=n)
solver = make_solver(problem, "fast", max_time=120.0)
times = []
for x0, W, u in zip(d[f"x0_{n}"], d[f"W_{n}"], d[f"u_guess_{n}"]):
    solver.reset()
    sol = solver.solve(x0, W, u_guess=u)
    times.append(sol.solve_time)
try:
    from threadpoolctl import threadpool_info
    threads = sorted({i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"})
except ImportError:  # (an environment without it: the count is unknown)
    threads = []
print(json.dumps({"times": times, "threads": threads}))
"""


def run_case(python: str, horizon: int, exported: bool, repo: Path) -> dict:
    """One fresh process: solve times [s] per problem and the BLAS thread counts seen."""
    env = {
        k: v for k, v in os.environ.items() if k not in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS")
    }
    env.pop("LFM_BLAS_THREADS", None)
    if exported:
        env["OPENBLAS_NUM_THREADS"] = "1"
    data = str(REPO / "tests" / "data" / "long_horizon_problems.npz")
    out = subprocess.run(
        [python, "-c", CHILD, str(horizon), data],
        capture_output=True,
        text=True,
        env=env,
        cwd=repo,
        check=True,
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--horizon", type=int, default=30, choices=(15, 30))
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--python", default=None, help="another environment's Python too")
    parser.add_argument("--repo", type=Path, default=None, help="its checkout (cwd)")
    args = parser.parse_args()
    cases = [(sys.executable, REPO, "this")]
    if args.python:
        cases.append((args.python, args.repo or REPO, "other"))
    times: dict[tuple[str, bool], list] = {}
    threads: dict[tuple[str, bool], list] = {}
    for _ in range(args.repeats):  # alternating, so that the load falls on every case alike
        for python, repo, label in cases:
            for exported in (True, False):
                res = run_case(python, args.horizon, exported, repo)
                times.setdefault((label, exported), []).append(res["times"])
                threads[label, exported] = res["threads"]
    print(f"N = {args.horizon}, {args.repeats} alternating runs; median per problem [s]")
    for (label, exported), runs in times.items():
        med = np.median(np.array(runs), axis=0)
        what = "OPENBLAS_NUM_THREADS=1" if exported else "nothing exported     "
        print(
            f"  {label:5} {what}  BLAS threads {threads[label, exported]}  "
            + "  ".join(f"{t:7.2f}" for t in med)
            + f"   sum {med.sum():7.2f}"
        )


if __name__ == "__main__":
    main()
