"""The package stays readable in pieces: no module over 600 lines, no class over 400, no function
over 80 (issue 51).

Lengths are counted as the code reads: a module's lines, and a class's or function's from its
``def``/``class`` line to its last line (``end_lineno - lineno + 1``, decorators not counted);
a method is measured on its own as well as inside its class. The whole check parses the package's
sources once: well under a second.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FOLDERS = ("agents", "merger", "scenarios", "shared", "src")
"""The package's sources (``src`` is ``fleetmap`` itself, the others its subpackages)."""

MODULE_LINES = 600
CLASS_LINES = 400
FUNCTION_LINES = 80


def breaches(path: str, source: str) -> dict[str, int]:
    """What in ``source`` (the module at ``path``) is over its limit, with its length in lines."""
    found: dict[str, int] = {}
    lines = len(source.splitlines())
    if lines > MODULE_LINES:
        found[path] = lines

    def walk(node: ast.AST, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                name = prefix + child.name
                length = (child.end_lineno or child.lineno) - child.lineno + 1
                limit = CLASS_LINES if isinstance(child, ast.ClassDef) else FUNCTION_LINES
                if length > limit:
                    found[f"{path}::{name}"] = length
                walk(child, name + ".")
            else:
                walk(child, prefix)

    walk(ast.parse(source), "")
    return found


def package_breaches() -> dict[str, int]:
    found: dict[str, int] = {}
    for folder in FOLDERS:
        for file in sorted((ROOT / folder).rglob("*.py")):
            found |= breaches(file.relative_to(ROOT).as_posix(), file.read_text(encoding="utf-8"))
    return found


def test_no_module_class_or_function_is_over_its_limit() -> None:
    found = package_breaches()
    assert not found, (
        f"over the limits (module {MODULE_LINES}, class {CLASS_LINES}, function {FUNCTION_LINES}): {found}"
    )


def _function(lines: int) -> str:
    return "def f():\n" + "    x = 1\n" * (lines - 1)


@pytest.mark.parametrize(
    ("source", "name"),
    [
        ("x = 1\n" * (MODULE_LINES + 1), "m.py"),
        ("class C:\n" + "    x = 1\n" * CLASS_LINES, "m.py::C"),
        (_function(FUNCTION_LINES + 1), "m.py::f"),
        ("class C:\n    " + _function(FUNCTION_LINES + 1).replace("\n", "\n    "), "m.py::C.f"),
        ("def g():\n    " + _function(FUNCTION_LINES + 1).replace("\n", "\n    "), "m.py::g.f"),
    ],
)
def test_the_check_finds_each_limit_passed(source: str, name: str) -> None:
    assert name in breaches("m.py", source)


def test_the_check_lets_each_limit_be_reached() -> None:
    source = "class C:\n    " + _function(FUNCTION_LINES).replace("\n", "\n    ")
    assert breaches("m.py", source + "\n" * (MODULE_LINES - len(source.splitlines()))) == {}


def undocumented_numbers(source: str) -> list[str]:
    """The module-level constants of ``source`` that hold a number (``NAME = 0.3``, ``math.radians(5)``)
    with no reason beside them: no docstring among the next two statements (a pair documented
    together), no comment on or above its line."""
    tree, lines = ast.parse(source), source.splitlines()
    out = []
    for i, node in enumerate(tree.body):
        if not (isinstance(node, ast.Assign) and len(node.targets) == 1 and isinstance(node.targets[0], ast.Name)):
            continue
        name = node.targets[0].id
        numbers = [c for c in ast.walk(node.value) if isinstance(c, ast.Constant) and type(c.value) in (int, float)]
        if not name.isupper() or not numbers:
            continue
        after = tree.body[i + 1 : i + 3]
        documented = any(isinstance(s, ast.Expr) and isinstance(s.value, ast.Constant) for s in after)
        commented = "#" in lines[node.lineno - 1] or lines[node.lineno - 2].lstrip().startswith("#")
        if not (documented or commented):
            out.append(name)
    return out


def test_every_number_the_algorithm_fixes_says_why_beside_it() -> None:
    # (well under a second) issue 51: a value that is not a parameter is a named constant with its reason
    found = {
        str(p.relative_to(ROOT)): names
        for folder in ("agents", "merger", "shared/core")
        for p in sorted((ROOT / folder).rglob("*.py"))
        if (names := undocumented_numbers(p.read_text(encoding="utf-8")))
    }
    assert not found
    assert undocumented_numbers('A = 1\n"""Why."""\nB = 2.5\nC = "text"\n') == ["B"]
