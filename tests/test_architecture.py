"""The core is ROS-free: no module under lego_loam_py/core imports rclpy or any ROS message package; and what the
code cites of the original resolves inside the repository (docs/original.md)."""
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


REPO = CORE.parents[1]


def cited_sections(text: str) -> set[str]:
    """The sections and quirks of docs/original.md that ``text`` cites: '§6.2', 'quirk 8.5', 'quirks 8.1, 8.10'."""
    import re

    cited = set(re.findall(r'§(\d+(?:\.\d+)?)', text))
    for group in re.findall(r'quirks? (8\.\d+(?:(?:, | and )8\.\d+)*)', text):
        cited.update(re.findall(r'8\.\d+', group))
    return cited


def test_every_citation_of_the_original_resolves_inside_the_repository():
    """Comments cite docs/original.md (§N, quirk 8.N), never a document outside the repository, and every
    section or quirk they cite is there."""
    import re

    doc = (REPO / 'docs' / 'original.md').read_text()
    present = set(re.findall(r'^## (\d+)\.', doc, re.M)) | set(re.findall(r'^\* \*\*(\d+\.\d+)', doc, re.M))
    quirks = doc[doc.index('## 8. Quirks'):doc.index('## 14.')]
    present |= {f'8.{n}' for n in re.findall(r'^(\d+)\. ', quirks, re.M)}
    assert {'8.1', '8.14', '6.2', '5.3', '14'} <= present   # (the parsing of the page itself)
    missing, outside = {}, []
    sources = [p for d in ('lego_loam_py', 'tests', 'benchmarks') for p in (REPO / d).rglob('*.py')]
    for path in sources:
        if path.name == 'test_architecture.py':   # (its patterns would cite themselves)
            continue
        text = path.read_text()
        if re.search(r'reference/LEGO_LOAM|reference §', text):
            outside.append(str(path.relative_to(REPO)))
        unknown = cited_sections(text) - present
        if unknown:
            missing[str(path.relative_to(REPO))] = sorted(unknown)
    assert not outside, f'cite docs/original.md instead: {outside}'
    assert not missing, missing
    assert cited_sections('see §6.2 and quirks 8.1, 8.10 and 8.11, quirk 8.5') == {'6.2', '8.1', '8.10', '8.11', '8.5'}
