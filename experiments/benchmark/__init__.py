"""The benchmark (``lfm-benchmark``): the solvers side by side on recorded closed-loop
problems, the horizon and scenario sweeps, the filter and one episode, and its checks."""

from experiments.benchmark.checks import CHECKS, run_checks
from experiments.benchmark.problems import DEFAULT_CONFIG, problem_from_config, record_problems
from experiments.benchmark.run import (
    DEFAULT_MAX_STEPS,
    DEFAULT_SOLVERS,
    all_failures,
    run_benchmark,
)
from experiments.benchmark.solvers import build_solver

__all__ = [
    "CHECKS",
    "DEFAULT_CONFIG",
    "DEFAULT_MAX_STEPS",
    "DEFAULT_SOLVERS",
    "all_failures",
    "build_solver",
    "problem_from_config",
    "record_problems",
    "run_benchmark",
    "run_checks",
]
