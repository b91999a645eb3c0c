"""Solver, particle-filter and episode benchmark: ``python scripts/benchmark.py --help``.

A thin command line over :func:`experiments.cli.benchmark_main` (also installed as
``lfm-benchmark``).
"""

from experiments.cli import benchmark_main

if __name__ == "__main__":
    raise SystemExit(benchmark_main())
