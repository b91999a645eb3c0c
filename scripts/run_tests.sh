#!/usr/bin/env bash
# Set up .venv, lint with ruff, and run the test suite on two worker processes (pytest-xdist).
# Locally the default run leaves out the long seed sweeps and trainings (@pytest.mark.slow; add
# -m slow for them alone); with CI=true (.ci/run) every test runs, the slow ones included.
# Extra arguments go to pytest (after the defaults, so they win). Fails when ruff finds a
# problem or when no test ran (pytest exit code 5).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup_env.sh test
# Tiny LAPACK calls dominate here; OpenBLAS threads spin-waiting on them slowed the suite 10x.
# The solvers set their own BLAS threads, but many tests call NumPy before any solver is
# built, and torch (the RL tests) reads OMP_NUM_THREADS: so the suite keeps both.
export OPENBLAS_NUM_THREADS="${OPENBLAS_NUM_THREADS:-1}" OMP_NUM_THREADS="${OMP_NUM_THREADS:-1}"
# Lint first (pyproject's [tool.ruff]: pycodestyle, pyflakes, pyupgrade, isort, bugbear and
# the complexity rule C901 at 15), then the format; either failing fails the run.
.venv/bin/ruff check .
.venv/bin/ruff format --check .
# Two workers, each test to whichever is free (a module fixture may be built in both).
defaults=(-n "${LFM_TEST_WORKERS:-2}" --dist load)
if [ "${CI:-}" = "true" ]; then
  defaults+=(-m "slow or not slow")  # every test, the slow ones too
fi
set +e
.venv/bin/python -m pytest "${defaults[@]}" "$@"
code=$?
set -e
if [ "$code" -eq 5 ]; then
  echo "run_tests.sh: pytest collected no tests; failing on purpose" >&2
  exit 1
fi
exit "$code"
