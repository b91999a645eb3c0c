"""The solvers set their processes' BLAS threads themselves (controllers/threads.py).

Each check runs in a fresh Python with ``OPENBLAS_NUM_THREADS`` and ``OMP_NUM_THREADS``
unset, so OpenBLAS starts with its own default (one thread per core); the counts are read
with threadpoolctl inside a solve and inside an evaluation task.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from controllers.threads import BLAS_THREADS_ENV, blas_threads

REPO = Path(__file__).resolve().parents[2]

SOLVE = """
import json
import numpy as np
from controllers.config import load_config
from controllers.solvers import make_solver
from controllers.threads import blas_thread_counts

before = blas_thread_counts()
problem = load_config("quick").make_problem()
solver = make_solver(problem, "fast")
seen = []
convexify = solver._convexify  # read the counts inside the solve, where BLAS runs
def spy(*args, **kwargs):
    seen.append(blas_thread_counts())
    return convexify(*args, **kwargs)
solver._convexify = spy
x0 = np.array([0.0, 0.0, 1.0, np.pi / 4])
W = problem.model.sample_latent_forecasts(
    np.zeros((problem.n_scenarios, problem.model.latent_dim)), problem.horizon,
    np.random.default_rng(0))
solver.solve(x0, W)
print(json.dumps({"before": before, "inside": seen[0] if seen else None}))
"""

TASK = """
import json
import numpy as np
from controllers.config import load_config
from controllers.threads import blas_thread_counts
from controllers.agents.registry import resolve_agents
from experiments.evaluation.task import _episode_task

seen = []

class Braking:  # no solver: only the task itself can have set the threads
    def __init__(self, config):
        pass
    def reset(self, seed=None):
        pass
    def act(self, obs):
        seen.append(blas_thread_counts())
        return np.array([-1.0, 0.0])

before = blas_thread_counts()
(spec,) = resolve_agents([Braking])
row = _episode_task(spec, load_config("quick"), 0, None, False)
assert row["error"] == "", row["error"]
print(json.dumps({"before": before, "inside": seen[0]}))
"""


def _run(script: str, **env_vars: str) -> dict:
    env = {
        k: v
        for k, v in os.environ.items()
        if k not in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", BLAS_THREADS_ENV)
    }
    env.update(env_vars, PYTHONPATH=str(REPO))
    out = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(script)],
        capture_output=True,
        text=True,
        env=env,
        cwd=REPO,
        timeout=300,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def _default_threads() -> int:
    """What OpenBLAS starts with here when nothing is exported (one per core, capped)."""
    return min(os.cpu_count() or 1, 64)


def test_a_solve_runs_blas_on_one_thread_when_nothing_is_exported():
    seen = _run(SOLVE)
    assert seen["inside"] is not None and seen["inside"]  # both NumPy's and SciPy's BLAS
    assert set(seen["inside"]) == {1}
    if _default_threads() > 1:  # (on one core the default is 1 anyway)
        assert max(seen["before"]) > 1


def test_an_evaluation_task_runs_blas_on_one_thread_when_nothing_is_exported():
    seen = _run(TASK)
    assert set(seen["inside"]) == {1}


@pytest.mark.skipif(_default_threads() < 2, reason="needs two cores to tell 2 from the default")
def test_the_override_sets_another_count():
    seen = _run(SOLVE, LFM_BLAS_THREADS="2")
    assert set(seen["inside"]) == {2}


def test_the_override_none_leaves_blas_alone():
    seen = _run(SOLVE, LFM_BLAS_THREADS="none")
    assert seen["inside"] == seen["before"]


@pytest.mark.parametrize("text", ["0", "-1", "two", "1.5", "5000"])
def test_a_bad_override_names_the_variable(text):
    with pytest.raises(ValueError, match="LFM_BLAS_THREADS"):
        blas_threads({BLAS_THREADS_ENV: text})


def test_the_default_is_one_and_none_means_leave_alone():
    assert blas_threads({}) == 1
    assert blas_threads({BLAS_THREADS_ENV: "3"}) == 3
    assert blas_threads({BLAS_THREADS_ENV: "None"}) is None
