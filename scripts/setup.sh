#!/usr/bin/env bash
# Install ReRadar with every extra (server, training, benchmark, plots) and its test tools into the current
# Python (3.11); a vehicle-side client needs only the base install (README). CPU torch 2.13.0 first so nothing
# pulls a CUDA build; the same steps as docker/Dockerfile.
set -euo pipefail
cd "$(dirname "$0")/.."
python -m pip install --quiet "torch==2.13.0"
python -m pip install --quiet -e ".[all,test]"
