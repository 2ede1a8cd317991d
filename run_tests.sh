#!/usr/bin/env bash
# Runs the test suite on this checkout, setting everything up first (install.sh is a no-op when the venv
# is up to date). Extra arguments go to pytest, e.g.  ./run_tests.sh -k pointcloud -x
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
bash "$ROOT/install.sh" --quiet
cd "$ROOT"
exec "${LEGO_LOAM_VENV:-$ROOT/.venv}/bin/python" -m pytest "$@"
