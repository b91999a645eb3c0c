"""A build of the fast solver's C library in a process of its own, for the cache tests.

``python -m tests.controllers.solvers.fast.cache_runs SYSTEM [BUILDS]`` (from the repository
root, ``$LFM_CACHE_DIR`` set by the test) builds the condensed model of ``paper`` (the
bicycle) or ``point_mass`` (the second system's) ``BUILDS`` times (forgetting the loaded
library in between, so each build reads the cache again), evaluates it once against the
NumPy backend and prints one JSON line: the backend, whether each build was a cache hit,
the library's path, and both merits. A damaged library that is loaded crashes this process,
never the test's.
"""

from __future__ import annotations

import json
import sys

import numpy as np

from controllers.problem import ScenarioProblem
from controllers.solvers.fast.codegen import build
from controllers.solvers.fast.condensed import CondensedModel


def problem_of(which: str) -> ScenarioProblem:
    if which == "paper":
        from experiments.benchmark.problems import problem_from_config

        return problem_from_config(n_scenarios=20)
    from tests.controllers.test_second_system import COST, NS, N, point_mass, point_mass_model

    model = point_mass_model(point_mass())
    return ScenarioProblem(model, COST, horizon=N, n_scenarios=NS, slack_penalty=1.0e3)


def merit(model: CondensedModel, problem: ScenarioProblem) -> float:
    rng = np.random.default_rng(0)
    ns, n = problem.n_scenarios, problem.horizon
    x0 = np.tile(np.asarray(problem.cost.x_goal, dtype=float) * 0.1, (ns, 1))
    W = rng.normal(0.0, 0.5, (ns, n, problem.nw))
    u = rng.uniform(problem.input_lower, problem.input_upper, (n, problem.nu)).ravel()
    x0, W = problem.check_data(x0, W)
    ro = model.evaluate(
        np.ascontiguousarray(x0.T),
        np.ascontiguousarray(W.transpose(1, 0, 2)),
        u,
        model.state_cost0(x0),
    )
    return float(ro.merit)


def main(which: str, builds: int = 1) -> None:
    problem = problem_of(which)
    hits = []
    for _ in range(builds):
        build.forget_loaded()
        model = CondensedModel(problem)
        hits.append(model.cache_hit)
    path = None
    if model.backend == "compiled-c":
        path = str(build.build_library(problem.system, problem.dt).path)
    reference = merit(CondensedModel(problem, backend="numpy"), problem)
    result = {
        "backend": model.backend,
        "cache_hits": hits,
        "path": path,
        "merit": merit(model, problem),
        "reference": reference,
    }
    print(json.dumps(result))


if __name__ == "__main__":
    main(sys.argv[1], int(sys.argv[2]) if len(sys.argv) > 2 else 1)
