"""ament_pep257 docstring check over the whole package."""

from pathlib import Path

from ament_pep257.main import main
import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]

# ament_pep257 skips directories whose name starts with '.' or '_' (.venv,
# .git, __pycache__, ...); these are colcon outputs someone may create here.
EXCLUDES = [str(REPO_ROOT / name) for name in ('build', 'install', 'log')]


@pytest.mark.linter
@pytest.mark.pep257
def test_pep257(monkeypatch):
    monkeypatch.chdir(REPO_ROOT)
    rc = main(argv=['.', 'test', '--exclude', *EXCLUDES])
    assert rc == 0, 'Found code style errors / warnings'
