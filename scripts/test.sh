#!/usr/bin/env bash
# The project's test command (README, .ci/run): lint, type-check the service and map store, run the tests.
# Uses the virtualenv scripts/setup.sh made (./.venv, or RERADAR_VENV) unless one is active or none exists.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=python
venv="${RERADAR_VENV:-.venv}"
if [[ -z "${VIRTUAL_ENV:-}" && -x "$venv/bin/python" ]]; then
    PY="$venv/bin/python"
fi
echo "== ruff"
"$PY" -m ruff check reradar_core reradar_cli service maps tests scripts benchmarks
echo "== mypy (service, maps, reradar_cli)"
"$PY" -m mypy service maps reradar_cli
echo "== pytest"
"$PY" -m pytest "$@"
