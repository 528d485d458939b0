"""
The layers: which packages of landmark_ros may import ROS, checked two ways.

1. Each ROS-free package (``core``, ``pipeline``, ``sim``, ``eval`` and the offline
   parts of ``mrclam``) is imported with all its modules in a fresh interpreter, and no
   ROS module may get loaded.
2. Every ``import`` statement in the package, lazy ones inside functions included, is
   read from the source: only ``ros/``, ``nodes/``, ``bag/``, ``mrclam/player.py`` and
   ``demo/`` may name rclpy or a message package.
"""

import ast
import fnmatch
import json
from pathlib import Path
import subprocess
import sys

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]

# Runs in a fresh interpreter so nothing imported by other tests (or by
# conftest) can leak into sys.modules. Prints a JSON report on its last line.
_PROBE = r"""
import fnmatch
import importlib
import ast
import fnmatch
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

ROS_FREE = ['landmark_ros.core', 'landmark_ros.fusion', 'landmark_ros.pipeline',
            'landmark_ros.sim', 'landmark_ros.eval', 'landmark_ros.mrclam.data',
            'landmark_ros.mrclam.config', 'landmark_ros.mrclam.offline',
            'landmark_ros.mrclam.calibrate', 'landmark_ros.mrclam.report']
"""Packages and modules that must load without ROS (with all their submodules)."""

MAY_IMPORT_ROS = ('landmark_ros/ros/*', 'landmark_ros/nodes/*', 'landmark_ros/mrclam/player.py',
                  'landmark_ros/mrclam/cli.py', 'landmark_ros/demo/*', 'landmark_ros/bag/*')
"""Source files allowed to import ROS (``mrclam/cli.py`` only lazily, for the player; ``bag/``
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
    sources = sorted((REPO_ROOT / 'landmark_ros').rglob('*.py'))
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
