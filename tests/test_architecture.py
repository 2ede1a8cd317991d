"""The house's rules: the core is ROS-free (no module under lego_loam_py/core imports rclpy or any ROS message
package); it is stage packages that import only the stages before them in a scan's path (ALLOWED); no module of the
package imports itself round a cycle at import time; and what the code cites of the original resolves inside the
repository (docs/original.md)."""

from __future__ import annotations

import ast
import importlib
import subprocess
import sys
from pathlib import Path

import pytest

CORE = Path(__file__).resolve().parents[1] / 'lego_loam_py' / 'core'
ROS_MODULES = (
    'rclpy',
    'sensor_msgs',
    'std_msgs',
    'geometry_msgs',
    'nav_msgs',
    'tf2_msgs',
    'cloud_msgs',
    'builtin_interfaces',
    'rosgraph_msgs',
    'lego_loam_py.ros',
)


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


# The stage packages of the core, and which parts of the core each may import. ``shared`` is the modules left directly
# in core/ (frames, geometry, voxel, pointcloud, ...): every stage may use them, they use no stage. A stage imports
# the stages before it in a scan's path, never one after: imageProjection's code knows nothing of the odometry, the
# odometry nothing of the mapping, the mapping nothing of localization; the pipeline joins them all.
STAGES = ('params', 'parity', 'projection', 'imu', 'odometry', 'loop', 'mapping', 'localization')
ALLOWED = {
    'shared': {'shared'},
    'params': {'shared', 'params'},
    'parity': {'shared', 'parity'},
    'projection': {'shared', 'params', 'parity', 'projection'},
    'imu': {'shared', 'params', 'imu'},
    'odometry': {'shared', 'params', 'parity', 'projection', 'imu', 'odometry'},
    'loop': {'shared', 'params', 'loop'},
    'mapping': {'shared', 'params', 'imu', 'loop', 'mapping'},
    'localization': {'shared', 'params', 'imu', 'loop', 'mapping', 'localization'},
    'pipeline': {'shared', *STAGES, 'pipeline'},
}
# What of the package outside core/ the core may import: its errors and its file formats (no simulator, no inputs,
# no ROS, no command line).
OUTSIDE_ALLOWED = {'lego_loam_py.errors', 'lego_loam_py.formats', 'lego_loam_py.__version__'}
MAX_SHARED_MODULES = 12


def part_of(module: str) -> str | None:
    """Which part of the core a dotted module name belongs to (None: outside core)."""
    parts = module.split('.')
    if parts[:2] != ['lego_loam_py', 'core']:
        return None
    if len(parts) == 2 or parts[2] in ('_libm_compat', '_feature_kernels'):
        return 'shared'
    return parts[2] if parts[2] in STAGES or parts[2] == 'pipeline' else 'shared'


def rule_violations(sources: dict[str, str]) -> list[str]:
    """``module -> its source`` of core modules: the imports their part may not make (every import, those inside
    functions too)."""
    found = []
    for module, text in sources.items():
        part = part_of(module)
        for node in ast.walk(ast.parse(text)):
            names = (
                [a.name for a in node.names]
                if isinstance(node, ast.Import)
                else [node.module]
                if isinstance(node, ast.ImportFrom) and node.module and node.level == 0
                else []
            )
            for name in names:
                if not name.startswith('lego_loam_py'):
                    continue
                target = part_of(name)
                if name == 'lego_loam_py' and isinstance(node, ast.ImportFrom):
                    name = 'lego_loam_py.' + ','.join(a.name for a in node.names)  # (its version)
                if target is None:
                    if not any(name == ok or name.startswith(ok + '.') for ok in OUTSIDE_ALLOWED):
                        found.append(f'{module} imports {name} (outside the core)')
                elif target not in ALLOWED[part]:
                    found.append(f'{module} ({part}) imports {name} ({target})')
    return found


def _core_sources() -> dict[str, str]:
    return {
        '.'.join(p.relative_to(CORE.parents[1]).with_suffix('').parts).removesuffix('.__init__'): p.read_text()
        for p in sorted(CORE.rglob('*.py'))
    }


def test_the_core_is_stage_packages_with_few_modules_between_them():
    """At least five stage packages, each naming its public API in its __init__, and at most 12 modules directly in
    core/ (what every stage shares)."""
    stages = [d.name for d in CORE.iterdir() if (d / '__init__.py').is_file()]
    assert set(STAGES) <= set(stages) and len(stages) >= 5
    shared = [p.name for p in CORE.glob('*.py') if p.name != '__init__.py']
    assert len(shared) <= MAX_SHARED_MODULES, sorted(shared)
    for stage in STAGES:
        init = (CORE / stage / '__init__.py').read_text()
        assert '__all__' in init and ast.get_docstring(ast.parse(init)), stage


def test_every_name_a_stage_exports_is_defined_where_it_says():
    """A stage's public API is resolved on first use: a name left behind when its definition moved or was renamed
    would only fail when someone asks for it."""
    for stage in STAGES:
        package = importlib.import_module(f'lego_loam_py.core.{stage}')
        missing = [name for name in package.__all__ if not hasattr(package, name)]
        assert not missing, (stage, missing)


def test_each_stage_imports_only_the_stages_before_it():
    violations = rule_violations(_core_sources())
    assert not violations, '\n'.join(violations)


def test_the_rule_check_finds_a_stage_that_imports_a_later_one():
    """The check itself can fail: imageProjection's code importing the mapping, the odometry importing the simulator,
    and a shared module importing a stage are each reported; the stages before are not."""
    sources = {
        'lego_loam_py.core.projection.ground': 'from lego_loam_py.core.mapping import MapOptimization\n',
        'lego_loam_py.core.odometry.features': 'def f():\n    from lego_loam_py.sim import scenarios\n',
        'lego_loam_py.core.frames': 'import lego_loam_py.core.params.types\n',
        'lego_loam_py.core.mapping.pose_graph': 'from lego_loam_py.core.loop import closure\n'
        'from lego_loam_py.formats import read_tum\n',
    }
    assert rule_violations(sources) == [
        'lego_loam_py.core.projection.ground (projection) imports lego_loam_py.core.mapping (mapping)',
        'lego_loam_py.core.odometry.features imports lego_loam_py.sim (outside the core)',
        'lego_loam_py.core.frames (shared) imports lego_loam_py.core.params.types (params)',
    ]


def import_time_edges(root: Path) -> dict[str, set[str]]:
    """``module -> the package modules it imports when it is imported``: the imports at module level (and in class
    bodies), each ``a.b.c`` also importing the packages ``a`` and ``a.b``."""
    modules = {
        '.'.join(p.relative_to(root.parent).with_suffix('').parts).removesuffix('.__init__'): p
        for p in root.rglob('*.py')
    }
    edges: dict[str, set[str]] = {m: set() for m in modules}

    def resolve(name: str) -> str | None:
        while name and name not in modules:
            name = name.rpartition('.')[0]
        return name or None

    def packages_of(name: str) -> list[str]:
        parts = name.split('.')
        return ['.'.join(parts[:i]) for i in range(1, len(parts))]

    for module, path in modules.items():
        body = list(ast.parse(path.read_text()).body)
        while body:
            node = body.pop()
            if isinstance(node, ast.ClassDef):
                body.extend(node.body)
            elif isinstance(node, (ast.If, ast.Try)):
                if isinstance(node, ast.If) and 'TYPE_CHECKING' in ast.dump(node.test):
                    continue
                body.extend(
                    node.body
                    + getattr(node, 'orelse', [])
                    + getattr(node, 'finalbody', [])
                    + [h for handler in getattr(node, 'handlers', []) for h in handler.body]
                )
            elif isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                targets = [node.module] + [f'{node.module}.{a.name}' for a in node.names]
            else:
                continue
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                for target in targets:
                    resolved = resolve(target) if target.startswith('lego_loam_py') else None
                    if resolved and resolved != module:  # (a module's own packages are loaded before it)
                        edges[module].update({resolved, *packages_of(resolved)} - {module, *packages_of(module)})
    return edges


def import_cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The cycles among modules (strongly connected parts of more than one module), Tarjan's way."""
    index, low, stack, on_stack, cycles, counter = {}, {}, [], set(), [], [0]

    def visit(node: str) -> None:
        index[node] = low[node] = counter[0]
        counter[0] += 1
        stack.append(node)
        on_stack.add(node)
        for nxt in edges.get(node, ()):
            if nxt not in index:
                visit(nxt)
                low[node] = min(low[node], low[nxt])
            elif nxt in on_stack:
                low[node] = min(low[node], index[nxt])
        if low[node] == index[node]:
            part = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                part.append(member)
                if member == node:
                    break
            if len(part) > 1:
                cycles.append(sorted(part))

    for node in sorted(edges):
        if node not in index:
            visit(node)
    return cycles


def test_no_module_of_the_package_imports_itself_round_a_cycle_at_import_time():
    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10000))
    edges = import_time_edges(CORE.parent)
    assert len(edges) > 100 and edges['lego_loam_py.core.pipeline']  # (the check reads the real modules)
    assert not import_cycles(edges), import_cycles(edges)
    # ... and it finds one: two modules importing each other at module level.
    assert import_cycles({'a': {'b'}, 'b': {'a'}, 'c': {'a'}}) == [['a', 'b']]


def test_importing_the_core_loads_no_ros_module():
    modules = sorted(_core_sources())
    code = (
        'import sys\n'
        + ''.join(f'import {m}\n' for m in modules)
        + f'bad = [m for m in sys.modules if m.split(".")[0] in {ROS_MODULES!r}]\n'
        + 'print(bad)\nsys.exit(1 if bad else 0)\n'
    )
    result = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stdout + result.stderr


# What no node loads before it is ready (benchmarks/bench_startup.py: 0.1-1 s of CPU each); a node imports them
# where they are used, or on a thread with their first input (LegoLoamNode.import_deferred).
HEAVY_AT_START = ('scipy.spatial', 'scipy.sparse', 'open3d', 'gtsam')


def test_no_node_imports_kd_trees_open3d_gtsam_or_the_message_code_generator_at_start_up():
    """Nor rosidl's code generator (lark, empy), which rosidl_generator_py imports with the first message type
    support unless told it is absent (lego_loam_py.ros does): 30 ms of CPU at every node's start."""
    for node in ('image_projection_node', 'feature_association_node', 'map_optimization_node', 'transform_fusion_node'):
        code = (
            f'import sys\nimport lego_loam_py.ros.{node}\n'
            'from rcl_interfaces.msg import ParameterEvent\n'
            'ParameterEvent.__class__.__import_type_support__()\n'
            f'print([m for m in {HEAVY_AT_START + ("lark", "em")!r} if m in sys.modules])\n'
        )
        result = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, timeout=120)
        assert result.returncode == 0 and result.stdout.strip() == '[]', (node, result.stdout, result.stderr)


# A run of the committed bag, every stage in this process, then the IMU check's fit on made-up turns; prints the
# heavy modules loaded by then.
_RUN_AND_FIT = """
import sys
import numpy as np
from lego_loam_py.core.imu.alignment import fit_alignment, shifted_increments
from lego_loam_py.core.params import Params
from lego_loam_py.offline import run_bag

imu_topic = sys.argv[2] or None
result = run_bag(sys.argv[1], Params(), imu_topic=imu_topic, max_scans=40, progress=False, front_end_process=False,
                 mapping_thread=False)
assert len(result.mapped) >= 10, len(result.mapped)
rng = np.random.default_rng(0)
turns = rng.normal(size=(20, 3)) * 0.05
quaternions = np.concatenate([np.sin(0.5 * turns), np.ones((20, 1))], axis=1)
quaternions /= np.linalg.norm(quaternions, axis=1)[:, None]
rates = rng.normal(size=(20, 3))
fit = fit_alignment(turns, lambda offsets: shifted_increments(quaternions, rates, rates, offsets))
assert fit.angle_deg == fit.angle_deg and fit.rotation_significance >= 0.0
print([m for m in sys.argv[3:] if m in sys.modules])
"""


@pytest.mark.parametrize('imu_topic', ['', '/imu/data'])
def test_the_scans_and_the_imu_check_need_no_kd_tree_library(imu_topic):
    """The neighbour searches are grids and the rotations core.frames': scipy.spatial (0.4 s of CPU to import) is
    left to what needs it (a search's rare tie, a loop closure, the calibration), so a node never loads it for its
    scans or its IMU. gtsam does come: the pose graph."""
    bag = CORE.parents[1] / 'bags' / 'campus_8s'
    done = subprocess.run(
        [sys.executable, '-c', _RUN_AND_FIT, str(bag), imu_topic, 'scipy.spatial', 'open3d', 'gtsam'],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip().splitlines()[-1] == "['gtsam']"


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
    quirks = doc[doc.index('## 8. Quirks') : doc.index('## 14.')]
    present |= {f'8.{n}' for n in re.findall(r'^(\d+)\. ', quirks, re.M)}
    for section, body in re.findall(r'^\* \*\*(\d+\.\d+)(.*?)(?=^\* \*\*|^## )', doc, re.M | re.S):
        present |= {f'{section}/{n}' for n in re.findall(r'^  (\d+)\. ', body, re.M)}  # its numbered steps
    assert {'8.1', '8.14', '6.2', '5.3', '14', '6.2/1', '6.2/10'} <= present  # (the parsing of the page itself)
    assert '6.3/1' not in present and '6.2/11' not in present
    missing, outside = {}, []
    sources = [p for d in ('lego_loam_py', 'tests', 'benchmarks') for p in (REPO / d).rglob('*.py')]
    for path in sources:
        if path.name == 'test_architecture.py':  # (its patterns would cite themselves)
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
    assert cited_sections('(§5.3, §6.2 steps 1, 8 and 10-11; §6.3 step 2)') == {
        '5.3',
        '6.2',
        '6.3',
        '6.2/1',
        '6.2/8',
        '6.2/10',
        '6.2/11',
        '6.3/2',
    }


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
    for error, code in (
        (UsageError('--loop N needs N >= 1'), 2),
        (ParameterError("unknown parameter 'x'"), 2),
        (BagError('bag not found: /nowhere'), 1),
    ):
        assert run_command(raising(error), None) == code
        assert capsys.readouterr().err == f'error: {error}\n'
    assert run_command(raising(KeyboardInterrupt()), None) == 130
    try:  # anything else is a bug: its traceback is not hidden
        run_command(raising(ZeroDivisionError('bug')), None)
    except ZeroDivisionError:
        pass
    else:
        raise AssertionError('an unexpected exception was swallowed')


def test_a_command_imports_only_its_own_module():
    """``lego_loam_py run ...`` parses with the offline module alone (not the player's rclpy, the simulator's or the
    viewer's dependencies); ``lego_loam_py --help`` with none; build_parser() still gives every command its
    arguments and handler."""
    from lego_loam_py.cli import COMMANDS, build_parser

    check = (
        'import sys; from lego_loam_py.cli import COMMANDS, main, build_parser;'
        'args = build_parser("run").parse_args(["run", "some.bag", "--no-imu"]);'
        'modules = [module for _, module, *_ in COMMANDS if module in sys.modules];'
        'print(args.handler.__module__, args.no_imu, modules, "rclpy" in sys.modules)'
    )
    done = subprocess.run([sys.executable, '-c', check], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ['lego_loam_py.offline', 'True', "['lego_loam_py.offline']", 'False']
    help_only = 'import sys; from lego_loam_py.cli import COMMANDS, build_parser; build_parser(""); '
    help_only += 'print([module for _, module, *_ in COMMANDS if module in sys.modules])'
    done = subprocess.run([sys.executable, '-c', help_only], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and done.stdout.strip() == '[]', done.stderr
    commands = build_parser()._subparsers._group_actions[0].choices
    assert set(commands) == {name for name, *_ in COMMANDS}
    assert all(parser.get_default('handler') is not None for parser in commands.values())


PACKAGE_DIR = REPO / 'lego_loam_py'
RUNNERS = ('offline', 'demo', 'launch')  # the modules of `lego_loam_py run`, `demo` and `launch`


def imports_between(modules: dict[str, Path]) -> set[tuple[str, str]]:
    """(importer, imported) pairs among ``modules`` (name -> source file), lazy imports inside functions
    included."""
    return {
        (name, other)
        for name, path in modules.items()
        for other in modules
        if other != name and f'lego_loam_py.{other}' in imported_modules(path)
    }


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
        ('demo', 'launch'),
        ('launch', 'offline'),
        ('offline', 'demo'),
    }


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
    homes = [
        path.relative_to(PACKAGE_DIR).as_posix()
        for path in sorted(PACKAGE_DIR.rglob('*.py'))
        if 'GraphMonitor' in defined_classes(path)
    ]
    assert homes == ['ros/graph_monitor.py'], homes
    direct = {}
    for name in RUNNERS + ('orchestration', 'supervisor'):
        found = {m for m in ros_imports(PACKAGE_DIR / f'{name}.py') if not m.startswith('lego_loam_py.ros')}
        if found:
            direct[name] = sorted(found)
    assert not direct, direct
    assert 'lego_loam_py.ros.graph_monitor' in imported_modules(PACKAGE_DIR / 'orchestration.py')  # (parsed)


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
        bad = {
            m
            for m in imported_modules(path)
            if m.startswith(('lego_loam_py.inputs', 'lego_loam_py.viewer')) or m.split('.')[0] == 'rerun'
        }
        if bad:
            offenders[str(path.relative_to(CORE))] = sorted(bad)
    assert not offenders, offenders


PACKAGE = CORE.parent
# What reads and writes a user's recordings and results never goes through the simulator: a real drive's ground
# truth is read by inputs/ (inputs/sidecars.py), which the simulator writes to, not the other way round.
NO_SIMULATOR = ('inputs', 'bag', 'sensors', 'ros', 'formats.py', 'offline.py', 'results.py', 'testing')


def imports_of(paths: list[Path], prefix: str) -> list[str]:
    """'<file name> imports <module>' for each import of the module ``prefix`` or one under it in ``paths``."""
    return [
        f'{path.name} imports {name}'
        for path in paths
        for name in sorted(imported_modules(path))
        if name == prefix or name.startswith(prefix + '.')
    ]


def test_recordings_and_results_are_read_without_the_simulator():
    paths = [
        p
        for entry in NO_SIMULATOR
        for p in ([PACKAGE / entry] if entry.endswith('.py') else sorted((PACKAGE / entry).rglob('*.py')))
    ]
    assert len(paths) > 20
    assert imports_of(paths, 'lego_loam_py.sim') == []


def test_benchmarks_import_nothing_of_the_tests():
    """What the tests and the benchmarks share lives in the package (lego_loam_py/testing), not in tests/."""
    benchmarks = sorted((PACKAGE.parent / 'benchmarks').glob('*.py'))
    assert len(benchmarks) > 10
    assert imports_of(benchmarks, 'tests') == []


def test_the_layering_checks_find_an_offender(tmp_path):
    reader = tmp_path / 'reader.py'
    reader.write_text(
        'import testsuite\n\ndef truth(bag):\n    from lego_loam_py.sim.output import world_of\n'
        '    from tests.support import scenes\n'
    )
    assert imports_of([reader], 'lego_loam_py.sim') == [
        'reader.py imports lego_loam_py.sim.output',
        'reader.py imports lego_loam_py.sim.output.world_of',
    ]
    assert imports_of([reader], 'tests') == [
        'reader.py imports tests.support',
        'reader.py imports tests.support.scenes',
    ]
