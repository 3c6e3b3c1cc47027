#!/usr/bin/env bash
# Validate docker/compose.yaml with a real Compose implementation (no Docker engine needed) and check that
# docker/Dockerfile keeps the README's install steps (scripts/setup.sh), a non-root user and a healthcheck.
#
# Needs `docker compose` (v2 plugin) or Debian's `docker-compose` (apt-get install --no-install-recommends
# docker-compose). Exit status 0 = valid.
set -euo pipefail
cd "$(dirname "$0")/.."

if docker compose version >/dev/null 2>&1; then
    COMPOSE=(docker compose)
elif command -v docker-compose >/dev/null 2>&1; then
    COMPOSE=(docker-compose)
else
    echo "check_compose: neither 'docker compose' nor 'docker-compose' is installed" >&2
    echo "  install one, e.g.: apt-get install -y --no-install-recommends docker-compose" >&2
    exit 2
fi

echo "== ${COMPOSE[*]} config (docker/compose.yaml)"
"${COMPOSE[@]}" --project-directory docker -f docker/compose.yaml config -q
rendered=$("${COMPOSE[@]}" --project-directory docker -f docker/compose.yaml config)
# Compose v2 renders ports in the long syntax, v1 as host_ip:published:target/protocol strings
grep -Eq "target: 8080|:8080/tcp" <<<"$rendered" || { echo "compose: service port 8080 not published" >&2; exit 1; }
grep -Eq "host_ip: 127\.0\.0\.1|127\.0\.0\.1:[0-9]+:8080" <<<"$rendered" \
    || { echo "compose: port 8080 must be published on 127.0.0.1 unless RERADAR_BIND says otherwise" >&2; exit 1; }
grep -q "reradar-maps:/data/maps" <<<"$rendered" || { echo "compose: maps volume missing" >&2; exit 1; }

echo "== Dockerfile checks"
python3 - <<'PY'
import re
import sys
from pathlib import Path

docker = Path("docker/Dockerfile").read_text()
setup = Path("scripts/setup.sh").read_text()
errors = []
# every pip install of the README's install must appear in the Dockerfile (torch from the CPU index there)
for line in re.findall(r"python -m pip install (.+)", setup):
    args = line.replace("--quiet", "").split()
    pkgs = [a.strip('"') for a in args if not a.startswith("-")]
    for pkg in pkgs:
        if pkg not in docker.replace('"', ""):
            errors.append(f"Dockerfile does not install {pkg!r} like scripts/setup.sh")
if not re.search(r"^USER\s+(?!root\b)\S+", docker, re.M):
    errors.append("Dockerfile must switch to a non-root USER")
if "HEALTHCHECK" not in docker:
    errors.append("Dockerfile needs a HEALTHCHECK")
if "download.pytorch.org/whl/cpu" not in docker:
    errors.append("Dockerfile must take torch from the CPU wheel index")
for args in re.findall(r"^COPY\s+(.+)$", docker, re.M):
    for src in args.split()[:-1]:
        if not src.startswith("--") and not Path(src).exists():
            errors.append(f"Dockerfile copies missing path {src!r}")
if errors:
    print("\n".join(errors), file=sys.stderr)
    sys.exit(1)
print("Dockerfile OK")
PY
echo "compose and Dockerfile OK"
