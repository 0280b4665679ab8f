"""No function in the lab is over :data:`MAX_LINES` lines: a study is a short pipeline over library steps, and a
long function is a study that grew a second job (``twohr bench`` was once ten studies in one 193-line function)."""

from __future__ import annotations

import ast
from pathlib import Path

LAB = Path(__file__).resolve().parents[1]
MAX_LINES = 80


def long_functions(source: str, max_lines: int = MAX_LINES) -> list[tuple[str, int, int]]:
    """(qualified name, first line, lines) of every function and method in ``source`` longer than ``max_lines``
    (from its ``def`` line to its last, decorators aside)."""
    found = []

    def visit(node: ast.AST, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef):
                name = f"{prefix}{child.name}"
                if (lines := child.end_lineno - child.lineno + 1) > max_lines:
                    found.append((name, child.lineno, lines))
                visit(child, f"{name}.")
            elif isinstance(child, ast.ClassDef):
                visit(child, f"{prefix}{child.name}.")
            else:
                visit(child, prefix)

    visit(ast.parse(source), "")
    return found


def test_the_scan_sees_a_long_method_and_a_long_nested_function():
    body = "\n".join(f"    x{i} = {i}" for i in range(MAX_LINES))
    source = f"class Study:\n    def run(self):\n    {body.replace(chr(10), chr(10) + '    ')}\n\n" \
             f"def short():\n    def inner():\n    {body.replace(chr(10), chr(10) + '    ')}\n    return inner\n" \
             "\nasync def fine():\n    pass\n"
    assert [(name, lines) for name, _, lines in long_functions(source)] == [("Study.run", MAX_LINES + 1),
                                                                            ("short", MAX_LINES + 3),
                                                                            ("short.inner", MAX_LINES + 1)]


def test_no_function_in_the_lab_is_over_80_lines():
    files = sorted(LAB.rglob("*.py"))
    assert len(files) > 50
    offenders = [f"{path.relative_to(LAB.parent)}:{line} {name} ({lines} lines)" for path in files
                 for name, line, lines in long_functions(path.read_text())]
    assert not offenders, f"functions over {MAX_LINES} lines: {offenders}"
