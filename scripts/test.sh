#!/usr/bin/env bash
# The project's test command (README, .ci/run): lint, type-check the service and map store, run the tests.
set -euo pipefail
cd "$(dirname "$0")/.."
echo "== ruff"
python -m ruff check reradar_core reradar_cli service maps tests scripts benchmarks
echo "== mypy (service, maps, reradar_cli)"
python -m mypy service maps reradar_cli
echo "== pytest"
python -m pytest "$@"
