#!/usr/bin/env bash
# Set up .venv (with the bench extra: csnlp) and run the solver / filter / episode benchmark,
# printing its report and writing results/benchmark.json. About 14 minutes on 2 idle cores.
# Extra arguments go to lfm-benchmark (e.g. --check, --quick, --seeds 3:6, --out other.json);
# with --check the exit status is 1 when a check fails (docs/benchmark.md#checks).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup_env.sh test,bench
# (No OPENBLAS_NUM_THREADS needed: the solvers and every evaluation task set BLAS to one
# thread themselves, LFM_BLAS_THREADS overrides it; the C library's OpenMP threads are
# agents.solver_threads.)
.venv/bin/lfm-benchmark "$@"
