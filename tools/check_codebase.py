#!/usr/bin/env python3
"""
Size limits of the landmark_ros source tree, read from the files (no import).

Rules (issue 25, item 5 and the README / docs part of item 1):

- ``module``: no module of the package (``landmark_ros/**/*.py``) over 600 lines.
- ``node-module``: no node module (``landmark_ros/nodes/*.py``) over 250 lines.
- ``function``: no function or method over 80 lines of code. A function's lines run
  from its ``def`` line to its last line, decorators and the docstring excluded;
  blank and comment lines count (they take a screen line too). A nested function
  counts in its own right and inside its parent.
- ``parameters``: no function with more than 8 parameters; a leading ``self`` or
  ``cls`` is not counted, ``*args`` and ``**kwargs`` count one each. Group the rest
  in a named record (a frozen dataclass).
- ``readme``: ``README.md`` at most 250 lines.
- ``docs``: every page of :data:`DOC_PAGES` present, each at most 400 lines.

Layer direction and cycles between folders are checked by ``test/test_layers.py``.

Run standalone from the repository root (``python tools/check_codebase.py``): it prints
the counts and every violation, and exits 1 if any rule is broken (``--rules`` limits
the rules checked, ``--root`` checks another tree). ``test/test_codebase.py`` runs the
same functions under ``make test``.
"""

import argparse
import ast
from dataclasses import dataclass
from pathlib import Path
import sys


@dataclass(frozen=True)
class Limits:
    """The numbers of the rules (lines are physical lines of the file)."""

    module_lines: int = 600
    node_module_lines: int = 250
    function_lines: int = 80
    parameters: int = 8
    readme_lines: int = 250
    doc_lines: int = 400


LIMITS = Limits()

PACKAGE = 'landmark_ros'
NODES = 'landmark_ros/nodes'
DOC_PAGES = ('docs/nodes.md', 'docs/parameters.md', 'docs/sensors.md', 'docs/association.md',
             'docs/bad-input.md', 'docs/evaluation.md', 'docs/architecture.md',
             'docs/benchmarks.md')

CODE_RULES = ('module', 'node-module', 'function', 'parameters')
"""The rules on the package's Python source."""
DOC_RULES = ('readme', 'docs')
"""The rules on README.md and docs/."""
RULES = CODE_RULES + DOC_RULES


@dataclass(frozen=True)
class Violation:
    """
    One broken rule, where, the measured value and the limit it exceeds.

    ``path`` is relative to the root, ``name`` the qualified name of a function or
    ``''``; ``value`` is -1 for a missing file.
    """

    rule: str
    path: str
    name: str
    value: int
    limit: int

    def __str__(self):
        where = f'{self.path}:{self.name}' if self.name else self.path
        if self.value < 0:
            return f'{self.rule}: {where} is missing'
        return f'{self.rule}: {where} has {self.value} (limit {self.limit})'


@dataclass(frozen=True)
class FunctionSize:
    """Size of one function: qualified ``name``, first line, code lines, parameters."""

    name: str
    lineno: int
    lines: int
    parameters: int


def line_count(path):
    """Return the number of physical lines of a text file."""
    return len(path.read_text(encoding='utf-8').splitlines())


def _docstring_lines(node):
    """Return how many lines the docstring of a function node spans (0 if none)."""
    body = node.body
    if (body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant)
            and isinstance(body[0].value.value, str)):
        return body[0].end_lineno - body[0].lineno + 1
    return 0


def parameter_count(args):
    """Return the parameters of an ``ast.arguments``, a leading self/cls excluded."""
    positional = [a.arg for a in args.posonlyargs + args.args]
    if positional and positional[0] in ('self', 'cls'):
        positional = positional[1:]
    return (len(positional) + len(args.kwonlyargs) + (args.vararg is not None)
            + (args.kwarg is not None))


def function_sizes(source, filename='<source>'):
    """Return a :class:`FunctionSize` for every function and method of a source text."""
    sizes = []

    def visit(node, prefix):
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
                name = prefix + child.name
                lines = child.end_lineno - child.lineno + 1 - _docstring_lines(child)
                sizes.append(FunctionSize(name, child.lineno, lines,
                                          parameter_count(child.args)))
                visit(child, name + '.')
            elif isinstance(child, ast.ClassDef):
                visit(child, prefix + child.name + '.')
            else:
                visit(child, prefix)

    visit(ast.parse(source, filename), '')
    return sizes


def package_modules(root):
    """Return the package's Python files under ``root``, sorted."""
    return sorted((root / PACKAGE).rglob('*.py'))


def check_code(root, limits=LIMITS):
    """Return the violations of the module, node-module, function and parameter rules."""
    found = []
    for path in package_modules(root):
        relative = path.relative_to(root).as_posix()
        lines = line_count(path)
        if lines > limits.module_lines:
            found.append(Violation('module', relative, '', lines, limits.module_lines))
        if path.parent.relative_to(root).as_posix() == NODES \
                and lines > limits.node_module_lines:
            found.append(Violation('node-module', relative, '', lines,
                                   limits.node_module_lines))
        for size in function_sizes(path.read_text(encoding='utf-8'), str(path)):
            if size.lines > limits.function_lines:
                found.append(Violation('function', relative, size.name, size.lines,
                                       limits.function_lines))
            if size.parameters > limits.parameters:
                found.append(Violation('parameters', relative, size.name, size.parameters,
                                       limits.parameters))
    return found


def check_docs(root, limits=LIMITS, pages=DOC_PAGES):
    """Return the violations of the README and docs rules."""
    found = []
    readme = root / 'README.md'
    if not readme.is_file():
        found.append(Violation('readme', 'README.md', '', -1, limits.readme_lines))
    elif line_count(readme) > limits.readme_lines:
        found.append(Violation('readme', 'README.md', '', line_count(readme),
                               limits.readme_lines))
    for page in pages:
        path = root / page
        if not path.is_file():
            found.append(Violation('docs', page, '', -1, limits.doc_lines))
        elif line_count(path) > limits.doc_lines:
            found.append(Violation('docs', page, '', line_count(path), limits.doc_lines))
    return found


def check(root, rules=RULES, limits=LIMITS):
    """Return the violations of the given rules under ``root``."""
    found = []
    if set(rules) & set(CODE_RULES):
        found += check_code(root, limits)
    if set(rules) & set(DOC_RULES):
        found += check_docs(root, limits)
    return [v for v in found if v.rule in rules]


def summary(root, violations):
    """Return the report printed by the command line: counts, then each violation."""
    modules = package_modules(root)
    functions = sum(len(function_sizes(p.read_text(encoding='utf-8'), str(p)))
                    for p in modules)
    lines = [f'{len(modules)} modules, {functions} functions under {root / PACKAGE}']
    for rule in RULES:
        count = sum(v.rule == rule for v in violations)
        lines.append(f'{rule:12s} {count:4d} over the limit')
    lines += [str(v) for v in violations]
    return '\n'.join(lines)


def main(argv=None):
    """Print the counts and violations; return 1 if any rule is broken."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0].strip())
    parser.add_argument('--root', type=Path, default=Path(__file__).resolve().parents[1],
                        help='repository root to check (default: this checkout)')
    parser.add_argument('--rules', nargs='+', choices=RULES, default=list(RULES),
                        help='rules to check (default: all)')
    args = parser.parse_args(argv)
    violations = check(args.root, args.rules)
    print(summary(args.root, violations))
    return 1 if violations else 0


if __name__ == '__main__':
    sys.exit(main())
