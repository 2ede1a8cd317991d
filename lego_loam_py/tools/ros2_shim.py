"""A minimal ``ros2`` command for environments without ros2cli (ROS 2 from PyPI wheels).

Only ``ros2 run <package> <executable> [args...]`` is provided, resolved the way ros2cli does it: the
package's prefix comes from the ament index (AMENT_PREFIX_PATH) and the executable from
``<prefix>/lib/<package>/``. Errors and exit codes follow ros2cli.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Sequence

USAGE = 'usage: ros2 run [-h] [--prefix PREFIX] package_name executable_name ...'


def _package_prefix(package: str) -> str | None:
    for prefix in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep):
        if prefix and os.path.isfile(
            os.path.join(prefix, 'share', 'ament_index', 'resource_index', 'packages', package)
        ):
            return prefix
    return None


def _executables(prefix: str, package: str) -> list[str]:
    libdir = os.path.join(prefix, 'lib', package)
    if not os.path.isdir(libdir):
        return []
    return sorted(
        name
        for name in os.listdir(libdir)
        if os.path.isfile(os.path.join(libdir, name)) and os.access(os.path.join(libdir, name), os.X_OK)
    )


def run(argv: Sequence[str]) -> int:
    argv = list(argv)
    if not argv or argv[0] in ('-h', '--help'):
        print(USAGE)
        print('\nRun a package specific executable (lego_loam_py shim of ros2cli: only "run" exists).')
        return 0
    prefix_cmd: list[str] = []
    if argv[0] == '--prefix':
        if len(argv) < 2:
            print(USAGE, file=sys.stderr)
            return 2
        prefix_cmd = argv[1].split()
        argv = argv[2:]
    if len(argv) < 2:
        print(USAGE, file=sys.stderr)
        print('ros2 run: error: the following arguments are required: package_name, executable_name', file=sys.stderr)
        return 2
    package, executable, rest = argv[0], argv[1], argv[2:]
    prefix = _package_prefix(package)
    if prefix is None:
        print(f"Package '{package}' not found", file=sys.stderr)
        return 1
    candidates = _executables(prefix, package)
    if executable not in candidates:
        print('No executable found', file=sys.stderr)
        if candidates:
            print(f"Executables of '{package}': {', '.join(candidates)}", file=sys.stderr)
        return 1
    path = os.path.join(prefix, 'lib', package, executable)
    command = prefix_cmd + [path] + rest
    sys.stdout.flush()
    sys.stderr.flush()
    os.execvp(command[0], command)
    return 1  # not reached


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ('-h', '--help'):
        print(
            'usage: ros2 <command> [options]\n\nCommands:\n  run  Run a package specific executable\n\n'
            '(lego_loam_py shim: ros2cli is not installable from PyPI; only "ros2 run" is provided.)'
        )
        return 0
    if argv[0] != 'run':
        print(f"ros2: error: unknown command '{argv[0]}' (this shim only provides 'ros2 run')", file=sys.stderr)
        return 2
    return run(argv[1:])


if __name__ == '__main__':
    sys.exit(main())
