"""
The README tells the truth.

It is a front page with the commands and the index of docs/, and the parameter tables
are where it says they are.

The manual's own checks (generated pages, links, rejection reasons) are in
``test_docs.py``.
"""

import importlib.util
from pathlib import Path

from landmark_ros.pipeline.config import markdown_table
import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / 'README.md'
PAGES = ('nodes', 'parameters', 'sensors', 'association', 'bad-input', 'evaluation',
         'architecture', 'benchmarks')


def _config_classes():
    spec = importlib.util.spec_from_file_location('docs_generate', ROOT / 'docs' / 'generate.py')
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.config_classes()


@pytest.mark.parametrize('node, config_class', _config_classes(),
                         ids=lambda value: value if isinstance(value, str) else '')
def test_parameters_page_lists_every_parameter_with_its_default(node, config_class):
    page = (ROOT / 'docs' / 'parameters.md').read_text(encoding='utf-8')
    assert f'## {node}' in page
    assert markdown_table(config_class) in page


def test_ci_runs_the_readme_test_command():
    readme = README.read_text(encoding='utf-8')
    assert 'make test' in readme
    assert 'make test' in (ROOT / '.ci' / 'run').read_text(encoding='utf-8')


def test_readme_is_a_front_page():
    text = README.read_text(encoding='utf-8')
    assert len(text.splitlines()) <= 250
    for command in ('make demo', 'make test', 'make bench', 'make docs', 'colcon build',
                    'ros2 launch landmark_ros team.launch.py sim:=true'):
        assert command in text, command
    assert '](docs/demo.png)' in text


def test_readme_indexes_every_page_of_the_manual():
    text = README.read_text(encoding='utf-8')
    for page in PAGES:
        assert f'](docs/{page}.md)' in text, page
    assert '](CHANGELOG.md)' in text
