"""The benchmark (``lfm-benchmark``): the solvers side by side on recorded closed-loop
problems, the horizon and scenario sweeps, the filter and one episode, and its targets."""

from experiments.benchmark.problems import DEFAULT_CONFIG, problem_from_config, record_problems
from experiments.benchmark.run import (
    DEFAULT_MAX_STEPS,
    DEFAULT_SOLVERS,
    all_failures,
    run_benchmark,
)
from experiments.benchmark.solvers import build_solver
from experiments.benchmark.targets import speed_targets

__all__ = [
    "DEFAULT_CONFIG",
    "DEFAULT_MAX_STEPS",
    "DEFAULT_SOLVERS",
    "all_failures",
    "build_solver",
    "problem_from_config",
    "record_problems",
    "run_benchmark",
    "speed_targets",
]
