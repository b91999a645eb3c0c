"""Solver, particle-filter and episode benchmark: ``python scripts/benchmark.py --help``.

A thin command line over :func:`experiments.benchmark.run.main` (also installed as
``lfm-benchmark``).
"""

from experiments.benchmark import main

if __name__ == "__main__":
    raise SystemExit(main())
