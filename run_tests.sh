#!/usr/bin/env bash
# Runs the test suite on this checkout, setting everything up first (install.sh is a no-op when the venv
# is up to date). Extra arguments go to pytest, e.g.  ./run_tests.sh -k pointcloud -x
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
bash "$ROOT/install.sh" --quiet
cd "$ROOT"
VENV="${LEGO_LOAM_VENV:-$ROOT/.venv}"
# The linter and the formatter first (a second or two; pyproject.toml holds their rules): CI keeps the tree clean.
"$VENV/bin/ruff" check --quiet .
"$VENV/bin/ruff" format --check --quiet .
exec "$VENV/bin/python" -m pytest "$@"
