"""ament_flake8 over the whole package, as the ROS 2 buildfarm runs it."""

import json
from pathlib import Path
import subprocess
import sys

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]

# ament_flake8 already skips every directory whose name starts with '.' or '_'
# (.venv, .git, .hypothesis, __pycache__, ...) and any tree holding an
# AMENT_IGNORE file. These are colcon outputs someone may create in the repo.
EXCLUDES = [str(REPO_ROOT / name) for name in ('build', 'install', 'log')]

# flake8 lints in a pool of forked worker processes. Forked from the test process,
# which other tests have filled with DDS threads, a worker can crash and leave the
# pool waiting for ever: the linter runs in a fresh interpreter instead.
_RUN = r"""
import json, sys
from ament_flake8.main import main_with_errors
rc, errors = main_with_errors(argv=sys.argv[1:])
print(json.dumps({'rc': rc, 'errors': errors}))
"""


@pytest.mark.flake8
@pytest.mark.linter
def test_flake8():
    # ament_flake8 lints and walks os.getcwd(): the repo root.
    proc = subprocess.run([sys.executable, '-c', _RUN, '.', '--exclude', *EXCLUDES],
                          cwd=REPO_ROOT, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    report = json.loads(proc.stdout.strip().splitlines()[-1])
    assert report['rc'] == 0, \
        'Found %d code style errors / warnings:\n' % len(report['errors']) + \
        '\n'.join(report['errors'])
