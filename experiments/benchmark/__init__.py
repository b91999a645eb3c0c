"""The benchmark (``lfm-benchmark``): the solvers side by side on recorded closed-loop
problems, the horizon and scenario sweeps, the filter and one episode, and its targets."""

from experiments.benchmark.run import (
    DEFAULT_CONFIG,
    DEFAULT_SOLVERS,
    all_failures,
    build_parser,
    build_solver,
    main,
    parse_ints,
    parse_seeds,
    parse_threshold,
    problem_from_config,
    record_problems,
    run_benchmark,
    speed_targets,
)

__all__ = [
    "DEFAULT_CONFIG",
    "DEFAULT_SOLVERS",
    "all_failures",
    "build_parser",
    "build_solver",
    "main",
    "parse_ints",
    "parse_seeds",
    "parse_threshold",
    "problem_from_config",
    "record_problems",
    "run_benchmark",
    "speed_targets",
]
