"""Rooms a reader can hold in their head: no function in ``station/``, ``drivers/``, ``mocks/``, ``procedures/``
longer than 80 lines (ruff has no rule for length; its mccabe rule C901 holds the complexity at 15, in
pyproject.toml). Checked on the syntax tree of
the source, so a long function fails here whatever its formatting."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MAX_LINES = 80


def test_no_function_in_the_source_is_longer_than_80_lines():
    long = []
    parts = ("station", "drivers", "mocks", "procedures")
    for path in sorted(p for part in parts for p in (ROOT / part).rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                lines = node.end_lineno - node.lineno + 1
                if lines > MAX_LINES:
                    long.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.name} ({lines} lines)")
    assert not long, "functions over 80 lines (split them by what they do):\n" + "\n".join(long)

