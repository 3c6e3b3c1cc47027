#!/usr/bin/env bash
# Install ReRadar with every extra (server, training, benchmark, plots) and its test tools into a virtualenv; a
# vehicle-side client needs only the base install (README). The virtualenv is ./.venv by default
# (RERADAR_VENV=DIR to choose; an already activated virtualenv is used as it is). Needs Python 3.11 or 3.12 (RERADAR_PYTHON=/path/to/python
# to choose); on Debian/Ubuntu also the venv module: apt-get install python3-venv.
#
# torch is the CPU build (torch==2.13.0+cpu from the PyTorch CPU index: a plain `pip install torch` pulls the
# multi-GB CUDA build on Linux). Every version comes from constraints.txt, as in CI and docker/Dockerfile.
set -euo pipefail
cd "$(dirname "$0")/.."

TORCH_CPU_INDEX="https://download.pytorch.org/whl/cpu"

version_ok() {  # $1 = a python executable; 0 when it is CPython 3.11 or 3.12
    "$1" -c 'import sys; sys.exit(0 if (3, 11) <= sys.version_info[:2] <= (3, 12) else 1)' 2>/dev/null
}

if [[ -n "${VIRTUAL_ENV:-}" ]]; then
    venv="$VIRTUAL_ENV"
else
    venv="${RERADAR_VENV:-.venv}"
    if [[ ! -x "$venv/bin/python" ]]; then
        py=""
        for cand in "${RERADAR_PYTHON:-}" python3.12 python3.11 python3 python; do
            [[ -n "$cand" ]] && command -v "$cand" >/dev/null 2>&1 && version_ok "$cand" && { py="$cand"; break; }
        done
        if [[ -z "$py" ]]; then
            echo "setup: ReRadar needs Python 3.11 or 3.12; none found (tried python3.12, python3.11, python3," \
                 "python). Install one (Debian 12: apt-get install python3 python3-venv) or set RERADAR_PYTHON." >&2
            exit 2
        fi
        echo "== creating virtualenv $venv with $("$py" --version) ($(command -v "$py"))"
        "$py" -m venv "$venv" || {
            echo "setup: '$py -m venv' failed; on Debian/Ubuntu: apt-get install python3-venv" >&2; exit 2; }
    fi
fi
PY="$venv/bin/python"
version_ok "$PY" || { echo "setup: $venv uses $("$PY" --version); need Python 3.11 or 3.12" >&2; exit 2; }

# The PyTorch CPU index serves torch==2.13.0+cpu. Where it cannot be reached (an offline mirror), pip's
# configured indexes must provide that exact build: the install then fails rather than pull a CUDA torch.
torch_index=()
if "$PY" -c "import sys, urllib.request; urllib.request.urlopen('$TORCH_CPU_INDEX/torch/', timeout=10)" 2>/dev/null; then
    torch_index=(--extra-index-url "$TORCH_CPU_INDEX")
else
    echo "== $TORCH_CPU_INDEX unreachable: taking torch==2.13.0+cpu from pip's configured indexes"
fi
echo "== installing into $venv ($("$PY" --version))"
"$PY" -m pip install --quiet "${torch_index[@]}" -c constraints.txt "torch==2.13.0+cpu"
"$PY" -m pip install --quiet -c constraints.txt -e ".[all,test]"
echo "== done: $venv/bin/reradar (or 'source $venv/bin/activate', then 'reradar')"
