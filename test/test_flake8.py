"""ament_flake8 over the whole package, as the ROS 2 buildfarm runs it."""

from pathlib import Path

from ament_flake8.main import main_with_errors
import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]

# ament_flake8 already skips every directory whose name starts with '.' or '_'
# (.venv, .git, .hypothesis, __pycache__, ...) and any tree holding an
# AMENT_IGNORE file. These are colcon outputs someone may create in the repo.
EXCLUDES = [str(REPO_ROOT / name) for name in ('build', 'install', 'log')]


@pytest.mark.flake8
@pytest.mark.linter
def test_flake8(monkeypatch):
    # ament_flake8 lints and walks os.getcwd(): pin it to the repo root.
    monkeypatch.chdir(REPO_ROOT)
    rc, errors = main_with_errors(argv=['.', '--exclude', *EXCLUDES])
    assert rc == 0, \
        'Found %d code style errors / warnings:\n' % len(errors) + \
        '\n'.join(errors)
