#!/usr/bin/env bash
# Set up .venv and run the default test suite (slow seed sweeps excluded; add -m slow for them).
# Extra arguments go to pytest. Fails when no test ran (pytest exit code 5).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup_env.sh test
set +e
.venv/bin/python -m pytest "$@"
code=$?
set -e
if [ "$code" -eq 5 ]; then
  echo "run_tests.sh: pytest collected no tests; failing on purpose" >&2
  exit 1
fi
exit "$code"
