"""The README tells the truth: parameter tables and the test command match the code."""

from pathlib import Path

from landmark_ros.pipeline.config import FuserConfig, markdown_table, ObserverConfig
import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize('config_class', [ObserverConfig, FuserConfig])
def test_readme_lists_every_parameter_with_its_default(config_class):
    assert markdown_table(config_class) in (ROOT / 'README.md').read_text()


def test_ci_runs_the_readme_test_command():
    readme = (ROOT / 'README.md').read_text()
    assert 'make test' in readme
    assert 'make test' in (ROOT / '.ci' / 'run').read_text()
