"""
The size limits of the codebase (issue 25), checked by ``tools/check_codebase.py``.

The code rules (module, node-module, function and parameter sizes) and the README / docs
rules are separate tests, one per rule. A rule named in :data:`PENDING` is expected to fail
(strict xfail): the report shows it as XFAIL while the work it waits for has not landed,
and as a failure (XPASS) once it holds, so that the entry is then removed.
"""

import importlib.util
from pathlib import Path
import subprocess
import sys

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
SCRIPT = REPO_ROOT / 'tools' / 'check_codebase.py'

PENDING = set()
"""Rules that wait for work not landed yet, e.g. ``{'readme', 'docs'}`` before the README
and docs/ rewrite of issue 25 item 1 (landed: empty)."""


def _load_checker():
    spec = importlib.util.spec_from_file_location('check_codebase', SCRIPT)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


checker = _load_checker()


def _maybe_pending(rule):
    marks = [pytest.mark.xfail(strict=True, reason=f'{rule}: pending (see PENDING)')] \
        if rule in PENDING else []
    return pytest.param(rule, marks=marks)


@pytest.mark.parametrize('rule', checker.CODE_RULES)
def test_code_within_size_limits(rule):
    violations = checker.check(REPO_ROOT, (rule,))
    assert not violations, '\n'.join(map(str, violations))


@pytest.mark.parametrize('rule', [_maybe_pending(rule) for rule in checker.DOC_RULES])
def test_readme_and_docs_within_limits(rule):
    violations = checker.check(REPO_ROOT, (rule,))
    assert not violations, '\n'.join(map(str, violations))


def test_the_checker_sees_the_package():
    modules = checker.package_modules(REPO_ROOT)
    assert len(modules) > 20
    functions = [f for p in modules for f in checker.function_sizes(p.read_text(), str(p))]
    assert len(functions) > 300
    assert any(f.name.startswith('Fuser.') for f in functions), 'methods are counted'


def _lines(count, prefix=''):
    return ''.join(f'{prefix}x{i} = {i}\n' for i in range(count))


def _function(name, lines, docstring_lines=0):
    """Source of a function of exactly ``lines`` code lines, plus a docstring."""
    doc = ''
    if docstring_lines:
        doc = '    """' + '\n' * (docstring_lines - 1) + '    """\n'
    return f'def {name}():\n' + doc + _lines(lines - 1, '    ')


def _tree(root, limits):
    """Write a tree where every rule holds exactly at its limit."""
    package = root / 'landmark_ros'
    (package / 'nodes').mkdir(parents=True)
    (root / 'docs').mkdir()
    (package / '__init__.py').write_text('')
    (package / 'big.py').write_text(_lines(limits.module_lines))
    (package / 'nodes' / 'node.py').write_text(_lines(limits.node_module_lines))
    (package / 'funcs.py').write_text(
        _function('long', limits.function_lines, docstring_lines=30)
        + 'def wide(a, b, c, d, e, f, *args, **kwargs):\n    pass\n'
        + 'class C:\n    def method(self, a, b, c, d, e, f, g, h):\n        pass\n')
    (root / 'README.md').write_text('line\n' * limits.readme_lines)
    for page in checker.DOC_PAGES:
        (root / page).write_text('line\n' * limits.doc_lines)
    return package


def _break(root, package, rule, limits):
    """Break one rule by one line or one parameter (the mutations)."""
    if rule == 'module':
        (package / 'big.py').write_text(_lines(limits.module_lines + 1))
    elif rule == 'node-module':
        (package / 'nodes' / 'node.py').write_text(_lines(limits.node_module_lines + 1))
    elif rule == 'function':
        (package / 'extra.py').write_text(
            'class K:\n' + ''.join('    ' + line + '\n' for line in
                                   _function('f', limits.function_lines + 1).splitlines()))
    elif rule == 'parameters':
        (package / 'extra.py').write_text('def g(a, b, c, d, e, f, g, *args, **kwargs):\n'
                                          '    pass\n')
    elif rule == 'readme':
        (root / 'README.md').write_text('line\n' * (limits.readme_lines + 1))
    elif rule == 'docs':
        (root / checker.DOC_PAGES[-1]).write_text('line\n' * (limits.doc_lines + 1))
        (root / checker.DOC_PAGES[0]).unlink()


def test_a_tree_at_the_limits_passes(tmp_path):
    _tree(tmp_path, checker.LIMITS)
    assert checker.check(tmp_path) == []
    sizes = {s.name: s for s in checker.function_sizes((tmp_path / 'landmark_ros' /
                                                        'funcs.py').read_text())}
    assert sizes['long'].lines == checker.LIMITS.function_lines
    assert sizes['wide'].parameters == 8
    assert sizes['C.method'].parameters == 8


@pytest.mark.parametrize('rule', checker.RULES)
def test_each_rule_can_fail(tmp_path, rule):
    limits = checker.LIMITS
    package = _tree(tmp_path, limits)
    _break(tmp_path, package, rule, limits)
    violations = checker.check(tmp_path)
    assert violations and {v.rule for v in violations} == {rule}, violations
    expected = {'module': 1, 'node-module': 1, 'function': 1, 'parameters': 1,
                'readme': 1, 'docs': 2}[rule]
    assert len(violations) == expected, violations
    if rule == 'function':
        assert violations[0].name == 'K.f' and violations[0].value == 81
    if rule == 'parameters':
        assert violations[0].value == 9
    if rule == 'docs':
        assert sorted(v.value for v in violations) == [-1, limits.doc_lines + 1]


def test_the_script_prints_the_counts_and_fails_on_a_violation(tmp_path):
    package = _tree(tmp_path, checker.LIMITS)
    clean = subprocess.run([sys.executable, str(SCRIPT), '--root', str(tmp_path)],
                           capture_output=True, text=True, timeout=60)
    assert clean.returncode == 0, clean.stdout + clean.stderr
    assert 'function        0 over the limit' in clean.stdout
    _break(tmp_path, package, 'parameters', checker.LIMITS)
    broken = subprocess.run([sys.executable, str(SCRIPT), '--root', str(tmp_path)],
                            capture_output=True, text=True, timeout=60)
    assert broken.returncode == 1, broken.stdout + broken.stderr
    assert 'parameters      1 over the limit' in broken.stdout
    assert 'landmark_ros/extra.py:g has 9 (limit 8)' in broken.stdout
