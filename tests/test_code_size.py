"""Sizes that keep the product readable (issue 59): no module of the product over 400 lines, no function over 80.
The product is what the wheel installs (services/, shared/, transport/); tests and developer tools are not held to it."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PRODUCT = ("services", "shared", "transport")
MAX_MODULE_LINES = 400
MAX_FUNCTION_LINES = 80


def _modules() -> list[Path]:
    return sorted(p for pkg in PRODUCT for p in (ROOT / pkg).rglob("*.py"))


def long_functions(source: str, limit: int) -> list[tuple[str, int, int]]:
    """(name, first line, length) of every function or method of ``source`` longer than ``limit`` lines (decorators
    and docstring included)."""
    out = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            first = min([node.lineno] + [d.lineno for d in node.decorator_list])
            n = node.end_lineno - first + 1
            if n > limit:
                out.append((node.name, first, n))
    return out


def test_no_product_module_is_over_400_lines():
    assert _modules(), "no product modules found"
    big = {str(p.relative_to(ROOT)): n for p in _modules() if (n := len(p.read_text().splitlines())) > MAX_MODULE_LINES}
    assert not big, f"modules over {MAX_MODULE_LINES} lines: {big}"


def test_no_product_function_is_over_80_lines():
    long = [f"{p.relative_to(ROOT)}:{line} {name} ({n} lines)" for p in _modules()
            for name, line, n in long_functions(p.read_text(), MAX_FUNCTION_LINES)]
    assert not long, "functions over 80 lines:\n" + "\n".join(long)


def test_the_check_counts_a_long_function_and_its_decorators():
    body = "\n".join(f"    x{i} = {i}" for i in range(80))
    src = f"@staticmethod\ndef f():\n{body}\n\ndef g():\n    return 1\n"
    assert long_functions(src, 80) == [("f", 1, 82)]
    assert long_functions(src, 82) == []
