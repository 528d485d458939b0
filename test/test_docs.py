"""
The manual in docs/ tells the truth and holds together.

- ``docs/parameters.md`` and the schema tables of ``docs/nodes.md`` are what
  ``docs/generate.py`` writes from the code (regenerate with ``make docs``).
- ``docs/benchmarks.md`` is the page ``make bench`` writes (``bench/summary.py``).
- Every counter name the code counts is in ``docs/bad-input.md``.
- Every relative link of README.md, CHANGELOG.md and docs/*.md reaches a file, and its
  ``#anchor`` a heading of that file.
- README and the pages keep their sizes and carry no dated history.
"""

import ast
import importlib.util
from pathlib import Path
import re
import sys

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / 'docs'
PAGES = ('nodes', 'parameters', 'sensors', 'association', 'bad-input', 'evaluation',
         'architecture', 'benchmarks', 'localization', 'slam', 'slam-analysis')


def _load(path, name):
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


generate = _load(DOCS / 'generate.py', 'docs_generate')


def _markdown_files():
    return [ROOT / 'README.md', ROOT / 'CHANGELOG.md'] + sorted(DOCS.glob('*.md'))


# --- generated pages ---------------------------------------------------------------

def test_parameters_page_is_generated_from_the_config_classes():
    nodes = [node for node, _ in generate.config_classes()]
    assert {'landmark_observer', 'landmark_fuser', 'landmark_sim'} <= set(nodes)
    assert (DOCS / 'parameters.md').read_text(encoding='utf-8') == \
        generate.parameters_page(), 'docs/parameters.md is out of date: run make docs'


def test_schema_tables_are_generated_from_the_schemas():
    text = (DOCS / 'nodes.md').read_text(encoding='utf-8')
    tables = generate.schema_tables()
    assert {match.group(2) for match in generate.BLOCK.finditer(text)} == set(tables)
    assert generate.with_blocks(text, tables) == text, \
        'the schema tables of docs/nodes.md are out of date: run make docs'


def test_a_changed_parameter_shows_as_a_stale_page():
    page = generate.parameters_page()
    node, config_class = generate.config_classes()[0]
    from dataclasses import fields
    name = fields(config_class)[0].name
    assert f'`{name}`' in page
    assert page.replace(f'`{name}`', f'`{name}_renamed`', 1) != \
        (DOCS / 'parameters.md').read_text(encoding='utf-8')


def test_benchmarks_page_is_what_make_bench_writes():
    sys.path.insert(0, str(ROOT / 'bench'))
    try:
        summary = _load(ROOT / 'bench' / 'summary.py', 'bench_summary')
    finally:
        sys.path.remove(str(ROOT / 'bench'))
    page = (DOCS / 'benchmarks.md').read_text(encoding='utf-8')
    assert page.startswith(summary.PAGE_HEAD)
    assert not re.search(r'\b20\d\d-\d\d-\d\d\b', page), 'latest run only, no dates'
    makefile = (ROOT / 'Makefile').read_text(encoding='utf-8')
    assert '--markdown docs/benchmarks.md' in makefile
    assert not (ROOT / 'bench' / 'results.md').exists()


# --- rejection reasons and counters -----------------------------------------------

_NAME = re.compile(r'^[a-z][a-z0-9]*(?:_[a-z0-9]+)*$')
_COUNTER_SETS = re.compile(r'(COUNTERS|COUNTS|NOT_PROBLEMS)$')


def _problem_tables():
    from landmark_ros.core import covariance
    return {name: value for name, value in vars(covariance).items()
            if name.endswith('PROBLEMS') and isinstance(value, dict)}


def _strings(node, scope, tables):
    """Return the names a string or an f-string over a ``*PROBLEMS`` table gives."""
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
        return {node.value}
    if not isinstance(node, ast.JoinedStr):
        return set()
    prefix = ''.join(part.value for part in node.values if isinstance(part, ast.Constant))
    formatted = [part.value for part in node.values if isinstance(part, ast.FormattedValue)]
    if len(formatted) != 1:
        return set()
    if isinstance(formatted[0], ast.Subscript) and isinstance(formatted[0].value, ast.Name):
        table = formatted[0].value.id
    else:
        found = set(re.findall(r'(\w*PROBLEMS)\.items\(\)', ast.unparse(scope)))
        if len(found) != 1:
            return set()
        table = found.pop()
    return {prefix + name for name in tables.get(table, {}).values()}


def _counted_in(node, scope, tables):
    """Return the counter names one AST node counts."""
    if isinstance(node, ast.Call):
        func = node.func
        name = func.attr if isinstance(func, ast.Attribute) else getattr(func, 'id', '')
        if name == 'add' and isinstance(func, ast.Attribute) and node.args \
                and 'counters' in ast.unparse(func.value):
            return _strings(node.args[0], scope, tables)
        if name == 'reject':
            return set().union(*(_strings(arg, scope, tables) for arg in node.args[:2]))
        if name.endswith('Error') and len(node.args) > 1:
            return _strings(node.args[0], scope, tables)
    elif isinstance(node, ast.Tuple) and len(node.elts) == 2 \
            and isinstance(node.elts[1], (ast.UnaryOp, ast.Compare, ast.BinOp)):
        return _strings(node.elts[0], scope, tables)   # (reason, mask) row checks
    elif isinstance(node, ast.AugAssign) and isinstance(node.target, ast.Subscript):
        if re.search(r'count|reason', ast.unparse(node.target.value)):
            return _strings(node.target.slice, scope, tables)
    elif isinstance(node, ast.Assign) and len(node.targets) == 1 \
            and isinstance(node.targets[0], ast.Name) \
            and _COUNTER_SETS.search(node.targets[0].id):
        return {sub.value for sub in ast.walk(node.value)
                if isinstance(sub, ast.Constant) and isinstance(sub.value, str)}
    return set()


def counted_names(sources, tables):
    """
    Return the counter names the code counts, with where each is first counted.

    Parameters
    ----------
    sources : dict
        ``label -> Python source``.
    tables : dict
        The ``*PROBLEMS`` tables of ``core.covariance``, by name.

    Returns
    -------
    dict
        ``name -> label:line``.

    """
    names = {}
    for label, text in sources.items():
        tree = ast.parse(text)
        functions = [node for node in ast.walk(tree)
                     if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))]
        for node in ast.walk(tree):
            if not hasattr(node, 'lineno'):
                continue
            scope = tree
            for function in functions:
                if function.lineno <= node.lineno <= function.end_lineno:
                    scope = function
            for name in _counted_in(node, scope, tables):
                if _NAME.match(name) and '_' in name or name in _ONE_WORD:
                    names.setdefault(name, f'{label}:{node.lineno}')
    return names


_ONE_WORD = {'fused', 'associated', 'confirmed', 'deleted', 'merged', 'ambiguous', 'saves'}
"""Counters named by one word (other one-word strings the patterns meet are not names)."""


def _package_sources():
    package = ROOT / 'landmark_ros'
    return {str(path.relative_to(ROOT)): path.read_text(encoding='utf-8')
            for path in sorted(package.rglob('*.py'))}


def test_the_reason_collector_finds_each_pattern():
    source = """
def f(self, status, source):
    self.counters.add('made_up_added', 1)
    self.reject(source, 'made_up_rejected', 2)
    raise CloudError('made_up_error', 'detail')
    checks = [('made_up_check', ids < 0)]
    reasons['made_up_augmented'] += 1
    self.counters.add(f'pose_{COVARIANCE_PROBLEMS[status]}', 1)
    for code, name in COVARIANCE_RANGE_PROBLEMS.items():
        reasons[f'result_{name}'] += 1
MY_COUNTERS = ('made_up_listed',)
"""
    names = counted_names({'x.py': source}, _problem_tables())
    assert {'made_up_added', 'made_up_rejected', 'made_up_error', 'made_up_check',
            'made_up_augmented', 'made_up_listed', 'pose_covariance_not_psd',
            'result_covariance_too_small'} <= set(names)


def test_every_counted_reason_is_in_the_bad_input_page():
    names = counted_names(_package_sources(), _problem_tables())
    # The collector must still see the code's patterns (a refactor that hides them
    # from it would make this test pass vacuously).
    assert {'queue_overflow', 'internal_error', 'pose_covariance_not_psd',
            'noise_covariance_not_psd', 'result_covariance_too_small', 'gated_out',
            'invalid_id', 'missing_field', 'poses_in'} <= set(names)
    page = (DOCS / 'bad-input.md').read_text(encoding='utf-8')
    missing = {name: where for name, where in names.items() if f'`{name}`' not in page}
    assert not missing, f'counted in the code, not in docs/bad-input.md: {missing}'


# --- links --------------------------------------------------------------------------

_LINK = re.compile(r'!?\[[^\]]*\]\(([^)\s]+)(?:\s+"[^"]*")?\)')


def github_anchors(text):
    """Return the anchors GitHub gives the headings of a markdown text."""
    anchors, seen = set(), {}
    for line in _outside_code(text):
        match = re.match(r'^#{1,6}\s+(.*?)\s*#*\s*$', line)
        if not match:
            continue
        slug = re.sub(r'[^\w\- ]', '', match.group(1).lower()).replace(' ', '-')
        count = seen.get(slug, 0)
        seen[slug] = count + 1
        anchors.add(slug if count == 0 else f'{slug}-{count}')
    return anchors


def _outside_code(text):
    fenced = False
    for line in text.splitlines():
        if line.lstrip().startswith('```'):
            fenced = not fenced
            continue
        if not fenced:
            yield re.sub(r'`[^`]*`', '', line) if not line.startswith('#') else line


def broken_links(path, text):
    """Return the relative links of a markdown file that reach no file or heading."""
    broken = []
    for line in _outside_code(text):
        for target in _LINK.findall(line):
            if re.match(r'^[a-z]+:', target):
                continue
            file_part, _, anchor = target.partition('#')
            if not file_part:
                if anchor not in github_anchors(text):
                    broken.append(target)
                continue
            linked = (path.parent / file_part).resolve()
            if not linked.exists():
                broken.append(target)
            elif anchor and linked.suffix == '.md' and \
                    anchor not in github_anchors(linked.read_text(encoding='utf-8')):
                broken.append(target)
    return broken


def test_the_link_check_finds_a_broken_link_and_anchor():
    text = '# A title\n\n[ok](#a-title) [file](README.md) [gone](nowhere.md) [bad](#nope)\n'
    assert broken_links(ROOT / 'x.md', text) == ['nowhere.md', '#nope']


@pytest.mark.parametrize('path', _markdown_files(), ids=lambda path: path.name)
def test_relative_links_resolve(path):
    assert broken_links(path, path.read_text(encoding='utf-8')) == []


# --- sizes and history ------------------------------------------------------------

def test_readme_and_pages_keep_their_sizes():
    assert len((ROOT / 'README.md').read_text(encoding='utf-8').splitlines()) <= 250
    for page in PAGES:
        lines = (DOCS / f'{page}.md').read_text(encoding='utf-8').splitlines()
        assert len(lines) <= 400, f'docs/{page}.md has {len(lines)} lines'


@pytest.mark.parametrize('path', [ROOT / 'README.md'] + sorted(DOCS.glob('*.md')),
                         ids=lambda path: path.name)
def test_no_dated_history_in_readme_or_docs(path):
    text = path.read_text(encoding='utf-8')
    assert not re.search(r'\b20\d\d-\d\d-\d\d\b|\b\d\d:\d\d UTC\b', text), 'a date'
    assert not re.search(r'tried and dropped|before this (change|rule)', text, re.I)
