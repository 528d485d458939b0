"""
Static types of the ROS-free layers: mypy is clean and the public API is annotated.

Every module of ``core/``, ``pipeline/``, ``observer/`` and ``fuser/`` is in ``REQUIRED``:
its public functions and methods must be fully annotated, and mypy checks the packages with the
settings of ``mypy.ini``, reporting every error. A new module fails
``test_every_module_is_required`` until it is added to ``REQUIRED`` (and annotated).
"""

import ast
import importlib.util
from pathlib import Path
import subprocess
import sys

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ('landmark_ros/core', 'landmark_ros/fusion', 'landmark_ros/pipeline',
            'landmark_ros/observer', 'landmark_ros/fuser')

REQUIRED = [
    'landmark_ros.core',
    'landmark_ros.core.arrays',
    'landmark_ros.core._partial_consider',
    'landmark_ros.core._partial_geometry',
    'landmark_ros.core._partial_init',
    'landmark_ros.core._partial_model',
    'landmark_ros.core._partial_update',
    'landmark_ros.core._split_ci',
    'landmark_ros.core.association',
    'landmark_ros.core.covariance',
    'landmark_ros.core.curvature',
    'landmark_ros.core.ellipse',
    'landmark_ros.core.gating',
    'landmark_ros.core.gaussian',
    'landmark_ros.core.joint_compatibility',
    'landmark_ros.core.landmarks',
    'landmark_ros.core.partial',
    'landmark_ros.core.range_scale',
    'landmark_ros.core.pose2',
    'landmark_ros.core.sensors',
    'landmark_ros.fusion',
    'landmark_ros.fusion.compiled',
    'landmark_ros.fusion.landmark_map',
    'landmark_ros.fusion.methods',
    'landmark_ros.fusion.moves',
    'landmark_ros.fusion.records',
    'landmark_ros.fusion.source_sums',
    'landmark_ros.pipeline',
    'landmark_ros.pipeline.config',
    'landmark_ros.pipeline.counters',
    'landmark_ros.pipeline.partial_rows',
    'landmark_ros.pipeline.limits',
    'landmark_ros.pipeline.pose_buffer',
    'landmark_ros.pipeline.rows',
    'landmark_ros.pipeline.scan',
    'landmark_ros.observer',
    'landmark_ros.observer.observer',
    'landmark_ros.observer.partial',
    'landmark_ros.observer.precision',
    'landmark_ros.observer.rows',
    'landmark_ros.fuser',
    'landmark_ros.fuser.change_detection',
    'landmark_ros.fuser.change_reference',
    'landmark_ros.fuser.change_rows',
    'landmark_ros.fuser.fuser',
    'landmark_ros.fuser.map_file',
    'landmark_ros.fuser.partial',
    'landmark_ros.fuser.partial_consider',
    'landmark_ros.fuser.partial_sources',
    'landmark_ros.fuser.persistence',
    'landmark_ros.fuser.publishing',
    'landmark_ros.fuser.sources',
    'landmark_ros.fuser.track_file',
    'landmark_ros.fuser.track_score',
    'landmark_ros.fuser.track_screen',
    'landmark_ros.fuser.tracks',
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


def _is_public(name):
    """Return whether a name is public: no leading underscore, or a dunder (``__len__``)."""
    return not name.startswith('_') or (name.startswith('__') and name.endswith('__'))


def public_functions(path):
    """
    Return the public functions and methods of a module.

    Public: a public name (``_is_public``; ``__init__`` too, the constructor's
    parameters are public) in the module or in a public class, nested classes
    included; definitions inside ``if``/``try``/``with`` blocks count where the block
    is. Methods of private classes and functions nested in functions are private.

    Parameters
    ----------
    path : pathlib.Path
        Module file.

    Returns
    -------
    list of (str, ast.FunctionDef or ast.AsyncFunctionDef, bool)
        Qualified name, definition, and whether it is a method.

    """
    found = []

    def visit(body, prefix, in_class):
        for node in body:
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                if _is_public(node.name):
                    found.append((prefix + node.name, node, in_class))
            elif isinstance(node, ast.ClassDef):
                if _is_public(node.name):
                    visit(node.body, f'{prefix}{node.name}.', True)
            elif isinstance(node, (ast.If, ast.Try, ast.With)):
                blocks = [node.body, getattr(node, 'orelse', []), getattr(node, 'finalbody', [])]
                blocks += [handler.body for handler in getattr(node, 'handlers', [])]
                for block in blocks:
                    visit(block, prefix, in_class)

    visit(ast.parse(path.read_text(), filename=str(path)).body, '', False)
    return found


def missing_annotations(path):
    """
    Return the public functions and methods of a module that lack an annotation.

    Parameters
    ----------
    path : pathlib.Path
        Module file.

    Returns
    -------
    list of str
        ``'<line>: <name>: <what is missing>'``.

    """
    problems = []
    for name, function, is_method in public_functions(path):
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


def test_every_module_is_required():
    # No module of core/ or pipeline/ escapes the check, including new ones.
    modules = module_files()
    assert len(modules) >= len(REQUIRED) > 0
    missing = sorted(set(modules) - set(REQUIRED))
    assert not missing, f'add these modules to REQUIRED (and annotate them): {missing}'


@pytest.mark.parametrize('module', REQUIRED)
def test_public_api_annotated(module):
    problems = missing_annotations(module_files()[module])
    assert not problems, (
        f'{module}: public functions and methods without a parameter or return '
        'annotation:\n' + '\n'.join(problems))


def test_public_functions_are_seen():
    # The walk finds the real API (functions, methods, properties, dunders, static
    # methods), so the check above cannot pass by seeing nothing.
    files = module_files()
    seen = {module: {name for name, _, _ in public_functions(files[module])}
            for module in REQUIRED}
    assert sum(map(len, seen.values())) > 150
    assert {'compose', 'compose_jacobians', 'wrap_angle'} <= seen['landmark_ros.core.pose2']
    assert {'LandmarkMap.__init__', 'LandmarkMap.update', 'LandmarkMap.__len__',
            'LandmarkMap.source_names', 'UpdateResult.changed'} <= seen[
        'landmark_ros.fusion.landmark_map'] | seen['landmark_ros.fusion.records']
    assert {'Views.__getitem__', 'Views.concatenate', 'update'} <= seen[
        'landmark_ros.core._partial_model'] | seen['landmark_ros.core._partial_update']
    assert {'Fuser.fuse_queued', 'Fuser.snapshot'} <= seen['landmark_ros.fuser.fuser']
    assert not any('._' in name and not name.endswith('__')
                   for names in seen.values() for name in names)


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
        '    def _helper(self, a):\n'
        '        return a\n'
        '    class Inner:\n'
        '        def method(self, a) -> int:\n'
        '            return a\n'
        'class _Private:\n'
        '    def method(self, a):\n'
        '        return a\n'
        'if True:\n'
        '    def in_block(a: int):\n'
        '        def nested(b):\n'
        '            return b\n'
        '        return nested(a)\n'
        'async def coroutine(a, /, *, b: int) -> None:\n'
        '    pass\n')
    assert missing_annotations(source) == [
        '3: no_return: return',
        '5: no_parameter: a',
        '7: no_star: args, kwargs',
        '12: Public.__init__: a',
        '17: Public.build: return',
        '20: Public.static: a',
        '22: Public.__len__: return',
        '27: Public.Inner.method: a',
        '33: in_block: return',
        '37: coroutine: a',
    ]


def test_unannotated_function_fails_a_required_module(tmp_path, monkeypatch):
    # A real module with one public function stripped of its hints is reported.
    path = module_files()['landmark_ros.core.pose2']
    text = path.read_text()
    stripped = text.replace('def compose(a: ArrayLike, b: ArrayLike) -> NDArray[np.float64]:',
                            'def compose(a, b):')
    assert stripped != text
    copy = tmp_path / 'pose2.py'
    copy.write_text(stripped)
    assert missing_annotations(path) == []
    assert [p.split(': ', 1)[1] for p in missing_annotations(copy)] == [
        'compose: a, b, return']


@pytest.mark.slow
@pytest.mark.skipif(importlib.util.find_spec('mypy') is None,
                    reason='mypy is not installed (requirements-dev.txt has it)')
def test_mypy(tmp_path):
    modules = module_files()
    result = subprocess.run(
        [sys.executable, '-m', 'mypy', '--config-file', str(REPO_ROOT / 'mypy.ini'),
         '--cache-dir', str(tmp_path / 'cache'), '--no-color-output', *PACKAGES],
        cwd=REPO_ROOT, capture_output=True, text=True, timeout=300)
    output = (result.stdout + result.stderr).strip()
    # Every module read: a wrong path or an excluded file must not pass silently.
    expected = f'Success: no issues found in {len(modules)} source files'
    assert result.returncode == 0 and output == expected, f'mypy reports:\n{output}'
