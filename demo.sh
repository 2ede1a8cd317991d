#!/usr/bin/env bash
# The one-command demo: LeGO-LOAM's four nodes as separate processes over DDS on a recording, with a summary,
# the trajectory, the map and a PNG at the end (see README.md, "Demo").
#
#   ./demo.sh [BAG] [-o OUTDIR] [--rate R] [-p name:=value ...]     (default: bags/campus_8s -> output/demo-campus_8s/)
#
# Sets up the venv first when needed (install.sh --quiet: a no-op once it is up to date).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
bash "$ROOT/install.sh" --quiet
exec "${LEGO_LOAM_VENV:-$ROOT/.venv}/bin/lego_loam_py" demo "$@"
