"""landmark_ros.core must stay importable and usable without any ROS 2 package."""

import json
from pathlib import Path
import subprocess
import sys

REPO_ROOT = Path(__file__).resolve().parents[1]

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


import landmark_ros.core as core

submodules = []
for info in pkgutil.walk_packages(core.__path__, core.__name__ + '.', onerror=fail):
    importlib.import_module(info.name)
    submodules.append(info.name)

print(json.dumps({
    'core_file': core.__file__,
    'submodules': sorted(submodules),
    'ros_modules': sorted(m for m in sys.modules if forbidden(m)),
}))
"""


def test_core_imports_no_ros():
    # cwd = repo root puts the source tree first on sys.path ('-c' adds '').
    proc = subprocess.run(
        [sys.executable, '-c', _PROBE],
        cwd=REPO_ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, (
        'importing landmark_ros.core failed:\n' + proc.stdout + proc.stderr)
    report = json.loads(proc.stdout.strip().splitlines()[-1])

    assert Path(report['core_file']).resolve().is_relative_to(REPO_ROOT), report
    assert report['submodules'], (
        'no submodules found under landmark_ros.core: the check would pass vacuously')
    ros_packages = sorted({name.split('.')[0] for name in report['ros_modules']})
    assert not ros_packages, (
        'importing landmark_ros.core and its submodules %s pulled in ROS packages %s '
        '(%d modules)' % (report['submodules'], ros_packages, len(report['ros_modules'])))
