"""The identifier stays readable: no function in ``commission.ident`` longer than a screen (issue 22)."""

from __future__ import annotations

import ast
from pathlib import Path

import commission.ident

#: Lines of a function, from ``def`` to its last line, docstring included.
MAX_FUNCTION_LINES = 80


def test_no_identifier_function_is_longer_than_a_screen() -> None:
    package = Path(commission.ident.__file__).parent
    sources = sorted(package.glob("*.py"))
    assert len(sources) > 5  # the package itself, installed or checked out, not an empty folder
    long = []
    for source in sources:
        for node in ast.walk(ast.parse(source.read_text(encoding="utf-8"))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                lines = node.end_lineno - node.lineno + 1
                if lines > MAX_FUNCTION_LINES:
                    long.append(f"{source.name}:{node.lineno} {node.name} ({lines} lines)")
    assert not long, "functions over a screen: " + ", ".join(long)
