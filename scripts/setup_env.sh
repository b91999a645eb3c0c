#!/usr/bin/env bash
# Create (or reuse) the project's virtualenv in .venv and install the package with extras.
# Usage: bash scripts/setup_env.sh [EXTRAS]   (default extras: test)
set -euo pipefail
cd "$(dirname "$0")/.."
extras="${1:-test}"
python="${PYTHON:-python3}"
if [ ! -x .venv/bin/python ]; then
  "$python" -m venv .venv
fi
stamp=".venv/.installed-${extras//,/-}"
# Reinstall only when the project's dependencies changed since the last install.
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
  .venv/bin/python -m pip install --quiet --upgrade pip
  # The rl and test extras need torch: install the CPU wheel first (pinned), so that pip
  # does not pull an unpinned torch with several GB of CUDA packages.
  case ",${extras}," in
    *,rl,* | *,test,*) .venv/bin/python -m pip install --quiet "torch==2.13.0" ;;
  esac
  .venv/bin/python -m pip install --quiet -e ".[${extras}]"
  touch "$stamp"
fi
