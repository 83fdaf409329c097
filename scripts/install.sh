#!/usr/bin/env bash
# Installs AGG and what its tests need on a fresh machine (Debian/Ubuntu, Python 3.11, no GPU).
#
# torch is installed first and pinned (2.13.0, the CPU build on CPU machines): an unpinned torch would pull
# gigabytes of CUDA wheels. The package is then installed without build isolation, so pip never builds anything
# against a second torch. GPU images install a CUDA torch and gsplat instead: see docs/INSTALL.md.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}

need_apt=()
command -v g++ >/dev/null 2>&1 || need_apt+=(g++)
if [ ${#need_apt[@]} -gt 0 ]; then
  if command -v apt-get >/dev/null 2>&1; then
    echo "installing system packages: ${need_apt[*]}"
    SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO=sudo
    $SUDO apt-get update -qq && $SUDO apt-get install -y -qq "${need_apt[@]}"
  else
    echo "warning: missing ${need_apt[*]} and no apt-get; install them yourself" >&2
  fi
fi

# The service and its tests need redis-server (a private one per test, on a random loopback port).
bash scripts/install_service_deps.sh

$PY -m pip install -q --upgrade "pip>=23" >/dev/null
$PY -m pip install -q "torch==2.13.0"
$PY -m pip install -q --no-build-isolation -e ".[test]"
# Build the native CPU render kernels now (cached per machine), so the first render does not wait for it.
$PY -c "from agg.render import native; native.load()"
echo "agg installed: $($PY -m agg.cli --version)"
