#!/usr/bin/env bash
# Set up .venv and run the main job: the evaluation of the agents on the default (paper)
# config over a few seeds, writing results/paper/episodes.csv and results/paper/report.md.
# Extra arguments go to lfm-evaluate (e.g. --seeds 0:20 --jobs 2).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup_env.sh dist
# (No OPENBLAS_NUM_THREADS needed: the solvers and every evaluation task set BLAS to one
# thread themselves, LFM_BLAS_THREADS overrides it; the C library's OpenMP threads are
# agents.solver_threads.)
.venv/bin/lfm-evaluate --config configs/paper.yaml --agents nominal,pf,scenario,scenario_particles,robust,oracle \
  --seeds 0:50 --jobs 2 --out results/paper "$@"
