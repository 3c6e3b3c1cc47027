#!/usr/bin/env bash
# Validate the fleet deployment (docker/compose.yaml, docker/nginx.conf, docker/Dockerfile) with a real Compose
# implementation (no Docker engine needed) plus checks of what the docs promise: redis + scalable API
# replicas + worker + nginx, maps on a shared volume, health checks and resource limits everywhere, a slim
# non-root runtime image built from constraints.txt with the CPU torch wheel and without test tools.
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
services=$("${COMPOSE[@]}" --project-directory docker -f docker/compose.yaml config --services | sort | tr '\n' ' ')
[[ "$services" == "api nginx redis worker " ]] || { echo "compose: services are '$services'" >&2; exit 1; }

RENDERED="$rendered" python3 - <<'PY'
import os
import re
import sys
from pathlib import Path

rendered = os.environ["RENDERED"]
errors = []


def block(name: str) -> str:
    """The rendered YAML of one service (two-space indented under `services:`)."""
    m = re.search(rf"^  {name}:\n((?:    .*\n|\s*\n)+)", rendered, re.M)
    return m.group(1) if m else ""


for svc in ("redis", "api", "worker", "nginx"):
    b = block(svc)
    if not b:
        errors.append(f"compose: service {svc} missing")
        continue
    if "healthcheck:" not in b:
        errors.append(f"compose: {svc} has no healthcheck")
    if not re.search(r"limits:\n\s+cpus: .+\n\s+memory: .+", b):
        errors.append(f"compose: {svc} has no cpu + memory limits")
api, worker, nginx, redis = block("api"), block("worker"), block("nginx"), block("redis")
for name, b in (("api", api), ("worker", worker)):
    if "reradar-maps:/data/maps" not in b:
        errors.append(f"compose: {name} does not mount the shared maps volume")
    if "RERADAR_REDIS_URL: redis://redis:6379/0" not in b:
        errors.append(f"compose: {name} does not use the redis service")
if "ports:" in api or "container_name" in api:
    errors.append("compose: api must not publish ports or name its container (docker compose --scale api=N)")
# Compose v2 renders ports in the long syntax, v1 as host_ip:published:target/protocol strings
if not re.search(r"target: 8080|:8080/tcp", nginx):
    errors.append("compose: nginx does not publish port 8080")
if not re.search(r"host_ip: 127\.0\.0\.1|127\.0\.0\.1:[0-9]+:8080", nginx):
    errors.append("compose: port 8080 must be published on 127.0.0.1 unless RERADAR_BIND says otherwise")
if re.search(r"RERADAR_API_KEY: reradar-dev-key", rendered):
    errors.append("compose: no default operator key (replicas share the generated one on the maps volume)")
if not re.search(r"command:\n\s+- reradar\n\s+- worker\n", worker):
    errors.append("compose: worker does not run `reradar worker`")
if "--appendonly" not in redis or "volatile-ttl" not in redis:
    errors.append("compose: redis needs --appendonly yes (durable build jobs) and maxmemory-policy volatile-ttl")

conf = Path("docker/nginx.conf").read_text()
if not re.search(r"server\s+api:8080\s+resolve", conf):
    errors.append("nginx.conf: upstream must be `server api:8080 resolve` (every replica, re-resolved)")
if "proxy_pass http://reradar_api" not in conf:
    errors.append("nginx.conf: location / must proxy to the reradar_api upstream")
if not re.search(r"limit_conn\s+reradar_per_client\s+\d+", conf) or "client_header_timeout" not in conf:
    errors.append("nginx.conf: limit connections per client (limit_conn) and set client_header_timeout")

docker = Path("docker/Dockerfile").read_text()
stages = re.split(r"^FROM\s+", docker, flags=re.M)[1:]
if len(stages) < 2:
    errors.append("Dockerfile: needs a build stage and a slim runtime stage")
else:
    runtime = stages[-1]
    if not re.search(r"^USER\s+(?!root\b)\S+", runtime, re.M):
        errors.append("Dockerfile: the runtime stage must switch to a non-root USER")
    if "HEALTHCHECK" not in runtime:
        errors.append("Dockerfile: the runtime stage needs a HEALTHCHECK")
    if "pip install" in runtime:
        errors.append("Dockerfile: the runtime stage must not install packages (copy the build stage's venv)")
if "-c constraints.txt" not in docker:
    errors.append("Dockerfile: install with the pins of constraints.txt (-c constraints.txt)")
if "download.pytorch.org/whl/cpu" not in docker or "torch==2.13.0+cpu" not in docker:
    errors.append("Dockerfile: torch==2.13.0+cpu from the PyTorch CPU index")
if re.search(r"\[test\]|pytest|ruff|mypy|selenium", docker):
    errors.append("Dockerfile: test tools do not belong in the image")
setup = Path("scripts/setup.sh").read_text()
if "-c constraints.txt" not in setup or "torch==2.13.0+cpu" not in setup:
    errors.append("scripts/setup.sh must install torch==2.13.0+cpu and the rest with -c constraints.txt")
for args in re.findall(r"^COPY\s+(.+)$", docker, re.M):
    if "--from=" in args:
        continue
    for src in args.split()[:-1]:
        if not Path(src).exists():
            errors.append(f"Dockerfile copies missing path {src!r}")
if errors:
    print("\n".join(errors), file=sys.stderr)
    sys.exit(1)
print("compose services, nginx.conf and Dockerfile OK")
PY
echo "compose and Dockerfile OK"
