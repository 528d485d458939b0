"""
The layers of landmark_ros: which folder may import which, and which may import ROS.

Folders, lowest first (``LAYERS``); a module may import its own folder and the folders
ranked below it, never one ranked alongside or above it::

    core -> fusion -> pipeline -> observer | fuser | localizer -> sim -> ros -> nodes
         -> eval -> mrclam -> bag -> demo

``observer``, ``fuser`` and ``localizer`` share one rank: siblings that never import
each other (what they share lives in ``pipeline``). Checked from the source, lazy
imports inside functions included:

1. Direction: every import of another folder goes down (``test_imports_go_down``).
2. Privacy: no module imports a ``_private`` module (or name) of another folder.
3. No cycle between folders, tools included (``eval``, ``mrclam``, ``bag``, ``demo``),
   found on the import graph itself, whatever the ranks say.
4. ROS: each ROS-free package is imported with all its modules in a fresh interpreter
   and no ROS module may get loaded; only ``ros/``, ``nodes/``, ``bag/``,
   ``mrclam/player.py``, ``mrclam/through_nodes.py``, ``mrclam/cli.py``
   and ``demo/`` may name rclpy or a message
   package.

A mutation test copies the package, adds one back-import (and one private import,
one cycle) to the copy and sees each check fail on it.
"""

import ast
import fnmatch
import json
from pathlib import Path
import shutil
import subprocess
import sys

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
PACKAGE = 'landmark_ros'

LAYERS = (('core',), ('fusion',), ('pipeline',), ('observer', 'fuser', 'localizer'),
          ('sim',), ('ros',), ('nodes',), ('eval',), ('mrclam',), ('bag',), ('demo',))
"""The folders of the package, lowest first; a tuple of several is one rank of siblings."""

RANK = {folder: rank for rank, folders in enumerate(LAYERS) for folder in folders}

TEMPORARY_EXCEPTIONS: set = set()
"""``(file, imported module)`` pairs the checks let through for now, each with its reason."""


# --- Reading the imports ---------------------------------------------------------------------

def module_name(path, root):
    """Return the dotted module name of a source file under ``root`` (the repository)."""
    parts = list(path.relative_to(root).with_suffix('').parts)
    if parts[-1] == '__init__':
        parts.pop()
    return '.'.join(parts)


def imports_of(path, root):
    """
    Return every module a source file imports, anywhere in it, as absolute dotted names.

    ``from a.b import c`` gives ``a.b.c`` (``c`` may be a module or a name: both count),
    ``import a.b`` gives ``a.b``; relative imports are resolved against the file's package.
    """
    name = module_name(path, root)
    package = name if path.name == '__init__.py' else name.rpartition('.')[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ''
            if node.level:
                anchor = package.split('.')[:len(package.split('.')) - node.level + 1]
                base = '.'.join(anchor + ([base] if base else []))
            found.update(f'{base}.{alias.name}' for alias in node.names)
    return found


def folder_of(dotted):
    """Return the package folder a dotted ``landmark_ros.<folder>...`` name is in, or None."""
    parts = dotted.split('.')
    return parts[1] if len(parts) > 2 and parts[0] == PACKAGE else None


def is_private(dotted):
    """Return whether a dotted name goes through a ``_private`` module or name."""
    return any(part.startswith('_') and not part.startswith('__') for part in dotted.split('.'))


def package_imports(root):
    """Return ``[(file, its folder, imported name)]`` for every package import of the tree."""
    rows = []
    sources = sorted((root / PACKAGE).rglob('*.py'))
    for path in sources:
        relative = path.relative_to(root).as_posix()
        own = folder_of(module_name(path, root) + '.x')
        for imported in sorted(imports_of(path, root)):
            if imported.split('.')[0] == PACKAGE and (
                    relative, imported) not in TEMPORARY_EXCEPTIONS:
                rows.append((relative, own, imported))
    return rows


# --- The checks ------------------------------------------------------------------------------

def direction_problems(root):
    """Return the imports that do not go down the layers (or name an unknown folder)."""
    problems = []
    for relative, own, imported in package_imports(root):
        target = folder_of(imported)
        if own is None or target is None or target == own:
            continue
        if own not in RANK or target not in RANK:
            problems.append(f'{relative}: {imported}: folder not in LAYERS')
        elif RANK[target] >= RANK[own]:
            kind = 'a sibling' if RANK[target] == RANK[own] else 'a layer above'
            problems.append(f'{relative} ({own}) imports {imported} ({target}, {kind})')
    return problems


def privacy_problems(root):
    """Return the imports of a ``_private`` module or name of another folder."""
    return [f'{relative} ({own}) imports {imported}, private to {folder_of(imported)}/'
            for relative, own, imported in package_imports(root)
            if folder_of(imported) not in (None, own) and is_private(imported)]


def folder_graph(root):
    """Return ``{folder: set of folders it imports}`` over the whole package."""
    graph = {}
    for _, own, imported in package_imports(root):
        target = folder_of(imported)
        if own is not None:
            graph.setdefault(own, set())
            if target is not None and target != own:
                graph[own].add(target)
    return graph


def find_cycle(graph):
    """Return one cycle of a directed graph as a list of nodes (first == last), or None."""
    state = {}

    def visit(node, path):
        state[node] = 'open'
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 'open':
                return path[path.index(nxt):] + [nxt]
            if nxt not in state:
                cycle = visit(nxt, path + [nxt])
                if cycle:
                    return cycle
        state[node] = 'done'
        return None

    for start in sorted(graph):
        if start not in state:
            cycle = visit(start, [start])
            if cycle:
                return cycle
    return None


def layer_problems(root):
    """Return every problem the three source checks find in the tree under ``root``."""
    problems = direction_problems(root) + privacy_problems(root)
    cycle = find_cycle(folder_graph(root))
    if cycle:
        problems.append('cycle between folders: ' + ' -> '.join(cycle))
    return problems


# --- Tests on the package --------------------------------------------------------------------

def test_every_folder_has_a_layer():
    folders = sorted(p.name for p in (REPO_ROOT / PACKAGE).iterdir()
                     if (p / '__init__.py').exists())
    assert {'core', 'pipeline', 'observer', 'fuser', 'ros', 'nodes'} <= set(folders)
    assert not set(folders) - set(RANK), f'add to LAYERS: {set(folders) - set(RANK)}'


def test_imports_go_down():
    assert len(package_imports(REPO_ROOT)) > 200   # the scan sees the package
    problems = direction_problems(REPO_ROOT)
    assert not problems, 'imports against the layers:\n' + '\n'.join(problems)


def test_no_module_imports_a_private_module_of_another_folder():
    problems = privacy_problems(REPO_ROOT)
    assert not problems, 'private imports across folders:\n' + '\n'.join(problems)


def test_no_cycle_between_folders_or_tools():
    graph = folder_graph(REPO_ROOT)
    assert {'nodes', 'mrclam', 'bag'} <= set(graph) and graph['nodes']
    cycle = find_cycle(graph)
    assert cycle is None, 'folders import each other: ' + ' -> '.join(cycle)


def test_the_temporary_exceptions_are_still_needed():
    # An exception whose import is gone must be deleted, not kept "just in case".
    for relative, imported in TEMPORARY_EXCEPTIONS:
        path = REPO_ROOT / relative
        assert path.exists() and imported in imports_of(path, REPO_ROOT), (
            f'{relative} no longer imports {imported}: drop it from TEMPORARY_EXCEPTIONS')


def test_the_import_reader_resolves_relative_lazy_and_from_imports(tmp_path):
    folder = tmp_path / PACKAGE / 'fuser'
    folder.mkdir(parents=True)
    path = folder / 'x.py'
    path.write_text('from . import tracks\nfrom ..core import _arrays as a\n'
                    'def f():\n    import landmark_ros.nodes.fuser\n'
                    '    from landmark_ros.pipeline.rows import first_problems\n')
    assert imports_of(path, tmp_path) == {
        'landmark_ros.fuser.tracks', 'landmark_ros.core._arrays', 'landmark_ros.nodes.fuser',
        'landmark_ros.pipeline.rows.first_problems'}
    assert is_private('landmark_ros.core._arrays') and not is_private('landmark_ros.core')
    assert folder_of('landmark_ros.core') is None and folder_of('landmark_ros.core.x') == 'core'


def test_the_cycle_finder_finds_cycles_and_only_cycles():
    assert find_cycle({'a': {'b'}, 'b': {'c'}, 'c': set()}) is None
    assert find_cycle({'a': {'b'}, 'b': {'c'}, 'c': {'a'}}) == ['a', 'b', 'c', 'a']
    assert find_cycle({'a': {'b', 'c'}, 'b': {'c'}, 'c': {'b'}}) == ['b', 'c', 'b']


# --- Mutation test: the checks fail on a copy with one bad import ------------------------------

@pytest.fixture
def package_copy(tmp_path):
    """Return the root of a copy of the package (sources only), clean under the checks."""
    shutil.copytree(REPO_ROOT / PACKAGE, tmp_path / PACKAGE,
                    ignore=shutil.ignore_patterns('__pycache__', '*.pyc'))
    assert layer_problems(tmp_path) == []
    return tmp_path


def _append(root, relative, line):
    path = root / PACKAGE / relative
    path.write_text(path.read_text() + f'\n\ndef _mutation():\n    {line}\n')


@pytest.mark.parametrize('relative, line, expected', [
    # core reaching up to a node (a back-import across the whole stack)
    ('core/pose2.py', 'from landmark_ros.nodes import fuser',
     'landmark_ros/core/pose2.py (core) imports landmark_ros.nodes.fuser (nodes, a layer above)'),
    # the observer taking something from its sibling, the fuser
    ('observer/observer.py', 'from landmark_ros.fuser.tracks import Tracker',
     'landmark_ros/observer/observer.py (observer) imports landmark_ros.fuser.tracks.Tracker '
     '(fuser, a sibling)'),
    # the replay using the demo launcher again
    ('mrclam/player.py', 'from landmark_ros.demo import run',
     'landmark_ros/mrclam/player.py (mrclam) imports landmark_ros.demo.run (demo, a layer '
     'above)'),
])
def test_a_back_import_makes_the_direction_check_fail(package_copy, relative, line, expected):
    _append(package_copy, relative, line)
    assert direction_problems(package_copy) == [expected]


def test_a_private_import_makes_the_privacy_check_fail(package_copy):
    _append(package_copy, 'eval/metrics.py', 'from landmark_ros.core import _split_ci')
    assert privacy_problems(package_copy) == [
        'landmark_ros/eval/metrics.py (eval) imports landmark_ros.core._split_ci, private to '
        'core/']


def test_a_tool_cycle_makes_the_cycle_check_fail(package_copy):
    # bag/export.py imports mrclam: mrclam importing bag closes a cycle.
    _append(package_copy, 'mrclam/cli.py', 'from landmark_ros.bag import export')
    problems = layer_problems(package_copy)
    assert 'cycle between folders: bag -> mrclam -> bag' in problems, problems


def test_the_checks_run_on_a_copy_as_a_script_and_exit_nonzero(package_copy):
    # The same checks, as a separate process would run them on a tree, fail on the copy.
    _append(package_copy, 'pipeline/counters.py', 'import landmark_ros.fuser.fuser')
    script = ('import sys; sys.path.insert(0, sys.argv[2]); import test_layers as t; '
              'from pathlib import Path; problems = t.layer_problems(Path(sys.argv[1])); '
              'print("\\n".join(problems)); sys.exit(1 if problems else 0)')
    proc = subprocess.run([sys.executable, '-c', script, str(package_copy),
                           str(Path(__file__).parent)], capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert 'landmark_ros/pipeline/counters.py (pipeline) imports landmark_ros.fuser.fuser' \
        in proc.stdout


# --- ROS-free layers -------------------------------------------------------------------------

# Runs in a fresh interpreter so nothing imported by other tests (or by
# conftest) can leak into sys.modules. Prints a JSON report on its last line.
_PROBE = r"""
import fnmatch
import importlib
import json
import pkgutil
import sys

FORBIDDEN = ('rclpy', 'rcl', 'rcl_interfaces', 'rosidl*', '*_msgs', '*_srvs',
             '*_interfaces', 'rpyutils', 'ament_index_python')


def forbidden(name):
    top = name.split('.')[0]
    return any(fnmatch.fnmatchcase(top, pattern) for pattern in FORBIDDEN)


def fail(name):
    raise ImportError('could not import ' + name)


core = importlib.import_module(sys.argv[1])

submodules = [core.__name__]
for info in (pkgutil.walk_packages(core.__path__, core.__name__ + '.', onerror=fail)
             if hasattr(core, '__path__') else ()):
    importlib.import_module(info.name)
    submodules.append(info.name)

print(json.dumps({
    'core_file': core.__file__,
    'submodules': sorted(submodules),
    'ros_modules': sorted(m for m in sys.modules if forbidden(m)),
}))
"""


FORBIDDEN = ('rclpy', 'rcl', 'rcl_interfaces', 'rosidl*', '*_msgs', '*_srvs',
             '*_interfaces', 'rpyutils', 'ament_index_python', 'builtin_interfaces')

ROS_FREE = [f'landmark_ros.{folder}' for folder in
            ('core', 'fusion', 'pipeline', 'observer', 'fuser', 'localizer', 'sim', 'eval')
            if (REPO_ROOT / PACKAGE / folder / '__init__.py').exists()] + [
    'landmark_ros.mrclam.data', 'landmark_ros.mrclam.config', 'landmark_ros.mrclam.offline',
    'landmark_ros.mrclam.calibrate', 'landmark_ros.mrclam.report',
    'landmark_ros.mrclam.localize', 'landmark_ros.mrclam.localize_data',
    'landmark_ros.mrclam.localize_cli']
"""Packages and modules that must load without ROS (with all their submodules)."""

MAY_IMPORT_ROS = ('landmark_ros/ros/*', 'landmark_ros/nodes/*', 'landmark_ros/mrclam/player.py',
                  'landmark_ros/mrclam/through_nodes.py', 'landmark_ros/mrclam/cli.py',
                  'landmark_ros/mrclam/localize_nodes.py', 'landmark_ros/mrclam/slam_nodes.py',
                  'landmark_ros/demo/*', 'landmark_ros/bag/*')
"""Source files allowed to import ROS (``mrclam/cli.py`` only lazily, for the players; ``bag/``
converts messages)."""


@pytest.mark.parametrize('package', ROS_FREE)
def test_ros_free_package_imports_no_ros(package):
    # cwd = repo root puts the source tree first on sys.path ('-c' adds '').
    proc = subprocess.run(
        [sys.executable, '-c', _PROBE, package],
        cwd=REPO_ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, (
        f'importing {package} failed:\n' + proc.stdout + proc.stderr)
    report = json.loads(proc.stdout.strip().splitlines()[-1])

    assert Path(report['core_file']).resolve().is_relative_to(REPO_ROOT), report
    assert report['submodules'], f'no modules found under {package}: vacuous check'
    ros_packages = sorted({name.split('.')[0] for name in report['ros_modules']})
    assert not ros_packages, (
        'importing %s and its submodules %s pulled in ROS packages %s (%d modules)'
        % (package, report['submodules'], ros_packages, len(report['ros_modules'])))


def imported_modules(path):
    """Return the top-level names of every module a source file imports, anywhere."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name.split('.')[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            names.add(node.module.split('.')[0])
    return names


def test_only_the_ros_layers_import_ros():
    sources = sorted((REPO_ROOT / PACKAGE).rglob('*.py'))
    assert len(sources) > 20
    offenders = {}
    for path in sources:
        relative = path.relative_to(REPO_ROOT).as_posix()
        if any(fnmatch.fnmatchcase(relative, pattern) for pattern in MAY_IMPORT_ROS):
            continue
        ros = sorted(name for name in imported_modules(path)
                     if any(fnmatch.fnmatchcase(name, p) for p in FORBIDDEN))
        if ros:
            offenders[relative] = ros
    assert not offenders, (
        f'outside ros/, nodes/, bag/, mrclam/player, demo/: ROS imports {offenders}')


def test_the_import_scan_sees_lazy_imports(tmp_path):
    path = tmp_path / 'lazy.py'
    path.write_text('def f():\n    from sensor_msgs.msg import PointCloud2\n    import rclpy\n')
    assert {'sensor_msgs', 'rclpy'} <= imported_modules(path)
