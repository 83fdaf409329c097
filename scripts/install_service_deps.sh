#!/usr/bin/env bash
# Installs what the AGG service and its tests need beyond the Python package:
# - redis-server (Redis >= 6.2): `agg serve` starts its own when no --redis-url is given, and the service tests
#   start private ones on random loopback ports;
# - a Compose CLI (`docker compose` or `docker-compose`): the deployment test validates docker-compose.yml with
#   `config`, which needs no Docker daemon. Debian's docker-compose package (Compose 1.29) is enough for that.
# Idempotent: installs only what is missing. Debian/Ubuntu (apt-get); elsewhere it says what to install. Python
# dependencies come with `pip install -e .` (scripts/install.sh).
set -euo pipefail

have_compose() {
  { command -v docker >/dev/null 2>&1 && docker compose version >/dev/null 2>&1; } ||
    { command -v docker-compose >/dev/null 2>&1 && docker-compose version >/dev/null 2>&1; }
}

need=()
command -v redis-server >/dev/null 2>&1 || need+=(redis-server)
have_compose || need+=(docker-compose)
if [ ${#need[@]} -eq 0 ]; then
  echo "redis-server present: $(redis-server --version | head -n1)"
  exit 0
fi
if ! command -v apt-get >/dev/null 2>&1; then
  if [[ " ${need[*]} " == *" redis-server "* ]]; then
    echo "error: redis-server is missing and there is no apt-get; install Redis >= 6.2 (redis-server on PATH)" >&2
    exit 1
  fi
  echo "warning: no Docker Compose and no apt-get; the compose-file test will skip until one is installed" >&2
  exit 0
fi
SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO=sudo
echo "installing with apt-get: ${need[*]}"
$SUDO apt-get update -qq
DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${need[@]}"
# The Debian redis-server package may start a system Redis on 6379; AGG never uses it unless told to (--redis-url).
echo "redis-server present: $(redis-server --version | head -n1)"
