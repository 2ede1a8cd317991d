"""The core is ROS-free: no module under lego_loam_py/core imports rclpy or any ROS message package."""
from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

CORE = Path(__file__).resolve().parents[1] / 'lego_loam_py' / 'core'
ROS_MODULES = ('rclpy', 'sensor_msgs', 'std_msgs', 'geometry_msgs', 'nav_msgs', 'tf2_msgs', 'cloud_msgs',
               'builtin_interfaces', 'rosgraph_msgs', 'lego_loam_py.ros')


def imported_modules(path: Path) -> set[str]:
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
    return names


def test_core_sources_import_no_ros():
    offenders = {}
    files = sorted(CORE.rglob('*.py'))
    assert len(files) >= 4
    for path in files:
        bad = {m for m in imported_modules(path) if m.split('.')[0] in ROS_MODULES or m.startswith(ROS_MODULES)}
        if bad:
            offenders[str(path.relative_to(CORE))] = sorted(bad)
    assert not offenders, offenders


def test_importing_the_core_loads_no_ros_module():
    modules = [f'lego_loam_py.core.{p.stem}' for p in sorted(CORE.glob('*.py')) if p.stem != '__init__']
    code = ('import sys\n' + ''.join(f'import {m}\n' for m in modules) +
            'bad = [m for m in sys.modules if m.split(".")[0] in %r]\nprint(bad)\nsys.exit(1 if bad else 0)\n'
            % (ROS_MODULES,))
    result = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stdout + result.stderr
