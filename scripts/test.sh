#!/usr/bin/env bash
# Set up (if needed) and run the test suite. Extra arguments go to pytest.
#   bash scripts/test.sh             default suite (under ~20 min on 2 cores)
#   bash scripts/test.sh -m slow     the heavier checks
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh --dev
if [ "$#" -eq 0 ]; then
  set -- -m "not slow and not stock_blender"
fi
exec .venv/bin/python -m pytest -q "$@"
