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
    """The absolute imports of ``path``, those inside functions included; ``from a import b`` gives 'a' and 'a.b'
    (b may be a module)."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
            names.update(f'{node.module}.{alias.name}' for alias in node.names)
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


MAX_CORE_MODULE_LINES = 450


def test_every_core_module_holds_one_concept_in_at_most_450_lines():
    """An algorithm module that grows past 450 lines holds more than one concept (laser_odometry.py once held two
    odometry models, the correspondence search and the geometry in 788): split it by concept."""
    sizes = {path.name: len(path.read_text().splitlines()) for path in CORE.glob('*.py')}
    assert len(sizes) > 20 and max(sizes.values()) > 300   # (the rule reads the real modules)
    too_long = {name: lines for name, lines in sizes.items() if lines > MAX_CORE_MODULE_LINES}
    assert not too_long, too_long


def test_importing_the_core_loads_no_ros_module():
    modules = [f'lego_loam_py.core.{p.stem}' for p in sorted(CORE.glob('*.py')) if p.stem != '__init__']
    code = ('import sys\n' + ''.join(f'import {m}\n' for m in modules) +
            'bad = [m for m in sys.modules if m.split(".")[0] in %r]\nprint(bad)\nsys.exit(1 if bad else 0)\n'
            % (ROS_MODULES,))
    result = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stdout + result.stderr


REPO = CORE.parents[1]


def cited_sections(text: str) -> set[str]:
    """The sections, steps and quirks of docs/original.md that ``text`` cites: '§6.2', '§6.2 step 7' (as
    '6.2/7'), '§6.2 steps 1, 8 and 10', '§6.2 steps 5-10', 'quirk 8.5', 'quirks 8.1, 8.10'."""
    import re

    cited = set(re.findall(r'§(\d+(?:\.\d+)?)', text))
    for section, group in re.findall(r'§(\d+\.\d+),? steps? (\d+(?:-\d+)?(?:(?:, | and )\d+(?:-\d+)?)*)', text):
        for first, last in re.findall(r'(\d+)(?:-(\d+))?', group):
            cited.update(f'{section}/{n}' for n in range(int(first), int(last or first) + 1))
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
    for section, body in re.findall(r'^\* \*\*(\d+\.\d+)(.*?)(?=^\* \*\*|^## )', doc, re.M | re.S):
        present |= {f'{section}/{n}' for n in re.findall(r'^  (\d+)\. ', body, re.M)}   # its numbered steps
    assert {'8.1', '8.14', '6.2', '5.3', '14', '6.2/1', '6.2/10'} <= present   # (the parsing of the page itself)
    assert '6.3/1' not in present and '6.2/11' not in present
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
    assert cited_sections('(§5.3, §6.2 steps 1, 8 and 10-11; §6.3 step 2)') == \
        {'5.3', '6.2', '6.3', '6.2/1', '6.2/8', '6.2/10', '6.2/11', '6.3/2'}


BUILTIN_ERRORS = {'Exception', 'ValueError', 'RuntimeError', 'OSError', 'TypeError', 'KeyError', 'LookupError'}


def test_every_error_of_the_package_has_the_common_root():
    """An exception class the package defines derives from lego_loam_py.errors.LegoLoamError, so that the command
    line turns it into a message and an exit code in one place."""
    classes, offenders = [], []
    for path in sorted((REPO / 'lego_loam_py').rglob('*.py')):
        for node in ast.walk(ast.parse(path.read_text())):
            if not isinstance(node, ast.ClassDef):
                continue
            bases = {b.id if isinstance(b, ast.Name) else getattr(b, 'attr', '') for b in node.bases}
            if bases & BUILTIN_ERRORS or node.name.endswith('Error'):
                classes.append(node.name)
                if 'LegoLoamError' not in bases and path.name != 'errors.py':
                    offenders.append(f'{path.relative_to(REPO)}: {node.name}')
    assert len(classes) >= 10 and not offenders, offenders


def test_the_command_line_turns_errors_into_one_line_and_an_exit_code(capsys):
    from lego_loam_py.bag.io import BagError
    from lego_loam_py.cli import run_command
    from lego_loam_py.core.params import ParameterError
    from lego_loam_py.errors import UsageError

    def raising(error):
        def handler(args):
            raise error
        return handler

    assert run_command(lambda args: 0, None) == 0 and run_command(lambda args: None, None) == 0
    for error, code in ((UsageError('--loop N needs N >= 1'), 2), (ParameterError("unknown parameter 'x'"), 2),
                        (BagError('bag not found: /nowhere'), 1)):
        assert run_command(raising(error), None) == code
        assert capsys.readouterr().err == f'error: {error}\n'
    assert run_command(raising(KeyboardInterrupt()), None) == 130
    try:   # anything else is a bug: its traceback is not hidden
        run_command(raising(ZeroDivisionError('bug')), None)
    except ZeroDivisionError:
        pass
    else:
        raise AssertionError('an unexpected exception was swallowed')


PACKAGE_DIR = REPO / 'lego_loam_py'
RUNNERS = ('offline', 'demo', 'launch')   # the modules of `lego_loam_py run`, `demo` and `launch`


def imports_between(modules: dict[str, Path]) -> set[tuple[str, str]]:
    """(importer, imported) pairs among ``modules`` (name -> source file), lazy imports inside functions
    included."""
    return {(name, other) for name, path in modules.items() for other in modules
            if other != name and f'lego_loam_py.{other}' in imported_modules(path)}


def test_the_runners_do_not_import_each_other(tmp_path):
    """``run`` (offline), ``launch`` and the demo share the parameter arguments (cli), the override parsing
    (core.params), the outputs (outputs.py) and the pipeline's orchestration (orchestration.py, supervisor.py)
    instead of importing each other."""
    crossing = imports_between({name: PACKAGE_DIR / f'{name}.py' for name in RUNNERS})
    assert not crossing, crossing
    # (the rule is parsed: a lazy import of another runner is found)
    (tmp_path / 'demo.py').write_text('def main():\n    from lego_loam_py.launch import main_argv\n')
    (tmp_path / 'launch.py').write_text('import lego_loam_py.offline\n')
    (tmp_path / 'offline.py').write_text('from lego_loam_py import demo, outputs\n')
    assert imports_between({name: tmp_path / f'{name}.py' for name in RUNNERS}) == {
        ('demo', 'launch'), ('launch', 'offline'), ('offline', 'demo')}


def ros_imports(path: Path) -> set[str]:
    """The ROS modules (rclpy, message packages, lego_loam_py.ros) ``path`` imports, lazily or not."""
    return {m for m in imported_modules(path) if m.split('.')[0] in ROS_MODULES or m.startswith(ROS_MODULES)}


def test_the_process_supervisor_knows_no_ros(tmp_path):
    """supervisor.py starts, watches and stops processes: no rclpy, no message package, no lego_loam_py.ros, not
    even inside a function, and none of the commands built on it."""
    supervisor = PACKAGE_DIR / 'supervisor.py'
    commands = {f'lego_loam_py.{name}' for name in RUNNERS + ('orchestration', 'cli')}
    assert not ros_imports(supervisor), ros_imports(supervisor)
    assert not imported_modules(supervisor) & commands, imported_modules(supervisor) & commands
    # (the rule is parsed: lazy imports count)
    sample = tmp_path / 'sample.py'
    sample.write_text('def spin():\n    import rclpy\n    from lego_loam_py.ros import qos\n')
    assert ros_imports(sample) == {'rclpy', 'lego_loam_py.ros', 'lego_loam_py.ros.qos'}


def defined_classes(path: Path) -> set[str]:
    return {node.name for node in ast.walk(ast.parse(path.read_text())) if isinstance(node, ast.ClassDef)}


def test_the_graph_monitor_is_part_of_the_ros_layer():
    """The supervisor's ROS node (GraphMonitor) lives under lego_loam_py/ros; the runners, the orchestration and
    the supervisor define no class of that name and import no rclpy themselves (the orchestration reaches the ROS
    graph only through lego_loam_py.ros)."""
    homes = [path.relative_to(PACKAGE_DIR).as_posix() for path in sorted(PACKAGE_DIR.rglob('*.py'))
             if 'GraphMonitor' in defined_classes(path)]
    assert homes == ['ros/graph_monitor.py'], homes
    direct = {}
    for name in RUNNERS + ('orchestration', 'supervisor'):
        found = {m for m in ros_imports(PACKAGE_DIR / f'{name}.py') if not m.startswith('lego_loam_py.ros')}
        if found:
            direct[name] = sorted(found)
    assert not direct, direct
    assert 'lego_loam_py.ros.graph_monitor' in imported_modules(PACKAGE_DIR / 'orchestration.py')   # (parsed)


def test_the_sensor_decoders_are_an_input_layer_outside_the_core():
    """The packet and pcap decoders (lego_loam_py/sensors) import no ROS; the core imports none of them."""
    sensors = REPO / 'lego_loam_py' / 'sensors'
    decoders = sorted(p for p in sensors.glob('*.py') if p.name != '__init__.py')
    assert {p.stem for p in decoders} >= {'velodyne', 'ouster', 'pcap'}
    offenders = {}
    for path in decoders:
        bad = {m for m in imported_modules(path) if m.split('.')[0] in ROS_MODULES or m.startswith(ROS_MODULES)}
        if bad:
            offenders[path.name] = sorted(bad)
    for path in sorted(CORE.rglob('*.py')):
        bad = {m for m in imported_modules(path) if m.startswith('lego_loam_py.sensors')}
        if bad:
            offenders[str(path.relative_to(CORE))] = sorted(bad)
    assert not offenders, offenders


def test_the_inputs_and_the_viewer_know_no_ros_and_the_core_knows_neither():
    """The recordings' sources (lego_loam_py/inputs) and the viewer's logging (lego_loam_py/viewer) import no ROS
    (the live viewer's node is lego_loam_py/ros/viewer_node.py); the core imports neither, nor Rerun."""
    offenders = {}
    for package in ('inputs', 'viewer'):
        for path in sorted((PACKAGE_DIR / package).glob('*.py')):
            if ros_imports(path):
                offenders[f'{package}/{path.name}'] = sorted(ros_imports(path))
    assert len(list((PACKAGE_DIR / 'inputs').glob('*.py'))) >= 5
    for path in sorted(CORE.rglob('*.py')):
        bad = {m for m in imported_modules(path)
               if m.startswith(('lego_loam_py.inputs', 'lego_loam_py.viewer')) or m.split('.')[0] == 'rerun'}
        if bad:
            offenders[str(path.relative_to(CORE))] = sorted(bad)
    assert not offenders, offenders
