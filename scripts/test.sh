#!/usr/bin/env bash
# The test command: installs (idempotent) and runs the whole suite. Fails when no test is collected.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh
exec ${PYTHON:-python3} -m pytest -q -ra "$@"
