#!/usr/bin/env bash
# Installs what the AGG service needs beyond the Python package: redis-server (Redis >= 6.2; `agg serve` starts
# its own when no --redis-url is given, and the service tests start private ones on random loopback ports).
# Idempotent: does nothing when redis-server is already on PATH. Debian/Ubuntu (apt-get); elsewhere it says what
# to install. Python dependencies come with `pip install -e .` (scripts/install.sh).
set -euo pipefail

if command -v redis-server >/dev/null 2>&1; then
  echo "redis-server present: $(redis-server --version | head -n1)"
  exit 0
fi
if ! command -v apt-get >/dev/null 2>&1; then
  echo "error: redis-server is missing and there is no apt-get; install Redis >= 6.2 (redis-server on PATH)" >&2
  exit 1
fi
SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO=sudo
echo "installing redis-server with apt-get"
$SUDO apt-get update -qq
DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends redis-server
# The Debian package may start a system Redis on 6379; AGG never uses it unless told to (--redis-url).
echo "redis-server installed: $(redis-server --version | head -n1)"
