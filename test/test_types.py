"""
Static types of the ROS-free layers: mypy is clean and the public API is annotated.

``REQUIRED`` lists the modules whose public functions and methods must be fully
annotated; mypy checks them with the settings of ``mypy.ini``. The other modules of
``core/`` and ``pipeline/`` are not annotated yet: mypy still reads them (calls into
them are checked against whatever annotations they have) but does not report their
own errors. To require a module, add it to ``REQUIRED``; nothing else changes.
"""

import ast
import importlib.util
from pathlib import Path
import subprocess
import sys

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ('landmark_ros/core', 'landmark_ros/pipeline')

REQUIRED = [
    'landmark_ros.core',
    'landmark_ros.core._arrays',
    'landmark_ros.core.association',
    'landmark_ros.core.ellipse',
    'landmark_ros.core.gaussian',
    'landmark_ros.core.landmarks',
    'landmark_ros.core.partial',
    'landmark_ros.core.pose2',
    'landmark_ros.core.sensors',
    'landmark_ros.pipeline.config',
    'landmark_ros.pipeline.counters',
    'landmark_ros.pipeline.fuser',
    'landmark_ros.pipeline.map_file',
    'landmark_ros.pipeline.observer',
    'landmark_ros.pipeline.pose_buffer',
    'landmark_ros.pipeline.rows',
    'landmark_ros.pipeline.tracks',
    'landmark_ros.pipeline.views',
    # Not annotated yet: landmark_ros.core.landmark_map.
]


def module_files():
    """Return ``module name -> file`` for every module of ``PACKAGES``."""
    modules = {}
    for package in PACKAGES:
        for path in sorted((REPO_ROOT / package).glob('*.py')):
            parts = path.relative_to(REPO_ROOT).with_suffix('').parts
            if parts[-1] == '__init__':
                parts = parts[:-1]
            modules['.'.join(parts)] = path
    return modules


def missing_annotations(path):
    """
    Return the public functions and methods of a module that lack an annotation.

    Public: no leading underscore, except ``__init__`` (the constructor's parameters
    are public too); methods of private classes are private.

    Parameters
    ----------
    path : pathlib.Path
        Module file.

    Returns
    -------
    list of str
        ``'<line>: <name>: <what is missing>'``.

    """
    tree = ast.parse(path.read_text(), filename=str(path))
    functions = []
    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            functions.append((node.name, node, False))
        elif isinstance(node, ast.ClassDef) and not node.name.startswith('_'):
            functions += [(f'{node.name}.{item.name}', item, True) for item in node.body
                          if isinstance(item, (ast.FunctionDef, ast.AsyncFunctionDef))]
    problems = []
    for name, function, is_method in functions:
        short = name.rsplit('.', 1)[-1]
        if short.startswith('_') and short != '__init__':
            continue
        arguments = function.args
        positional = arguments.posonlyargs + arguments.args
        decorators = {ast.unparse(d) for d in function.decorator_list}
        if is_method and 'staticmethod' not in decorators and positional:
            positional = positional[1:]  # self or cls
        parameters = positional + arguments.kwonlyargs + [
            a for a in (arguments.vararg, arguments.kwarg) if a is not None]
        missing = [a.arg for a in parameters if a.annotation is None]
        if function.returns is None:
            missing.append('return')
        if missing:
            problems.append(f"{function.lineno}: {name}: {', '.join(missing)}")
    return problems


def test_required_modules_exist():
    unknown = sorted(set(REQUIRED) - set(module_files()))
    assert not unknown, f'REQUIRED names modules that do not exist: {unknown}'


@pytest.mark.parametrize('module', REQUIRED)
def test_public_api_annotated(module):
    problems = missing_annotations(module_files()[module])
    assert not problems, (
        f'{module}: public functions and methods without a parameter or return '
        'annotation:\n' + '\n'.join(problems))


def test_missing_annotations_are_found(tmp_path):
    # The check itself: every kind of omission is reported, nothing else is.
    source = tmp_path / 'sample.py'
    source.write_text(
        'def typed(a: int, *args: int, b: str = "", **kwargs: float) -> None:\n'
        '    pass\n'
        'def no_return(a: int):\n'
        '    pass\n'
        'def no_parameter(a, b: int) -> int:\n'
        '    return b\n'
        'def no_star(*args, **kwargs) -> None:\n'
        '    pass\n'
        'def _private(a):\n'
        '    pass\n'
        'class Public:\n'
        '    def __init__(self, a) -> None:\n'
        '        pass\n'
        '    def method(self, a: int) -> int:\n'
        '        return a\n'
        '    @classmethod\n'
        '    def build(cls, a: int):\n'
        '        return cls(a)\n'
        '    @staticmethod\n'
        '    def static(a) -> int:\n'
        '        return a\n'
        '    def __len__(self):\n'
        '        return 0\n'
        'class _Private:\n'
        '    def method(self, a):\n'
        '        return a\n')
    assert missing_annotations(source) == [
        '3: no_return: return',
        '5: no_parameter: a',
        '7: no_star: args, kwargs',
        '12: Public.__init__: a',
        '17: Public.build: return',
        '20: Public.static: a',
    ]


@pytest.mark.slow
@pytest.mark.skipif(importlib.util.find_spec('mypy') is None,
                    reason='mypy is not installed (requirements-dev.txt has it)')
def test_mypy(tmp_path):
    modules = module_files()
    pending = sorted(set(modules) - set(REQUIRED))
    config = (REPO_ROOT / 'mypy.ini').read_text()
    if pending:
        # Read, so calls into them are checked, but their own errors are not reported.
        config += f"\n[mypy-{','.join(pending)}]\nignore_errors = True\n"
    config_file = tmp_path / 'mypy.ini'
    config_file.write_text(config)
    result = subprocess.run(
        [sys.executable, '-m', 'mypy', '--config-file', str(config_file),
         '--cache-dir', str(tmp_path / 'cache'), '--no-color-output', *PACKAGES],
        cwd=REPO_ROOT, capture_output=True, text=True, timeout=300)
    output = (result.stdout + result.stderr).strip()
    # Every module read: a wrong path or an excluded file must not pass silently.
    expected = f'Success: no issues found in {len(modules)} source files'
    assert result.returncode == 0 and output == expected, f'mypy reports:\n{output}'
