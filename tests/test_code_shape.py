"""The shape the code keeps, read from the source: short functions, a thin prediction API.

A function's length counts its lines of code: the ``def`` line(s) and body, without its
docstring, blank lines and comment lines (nested functions count in their parent too).
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MAX_FUNCTION_LINES = 80
MAX_PREDICTION_API_LINES = 300


def code_lines(lines: list[str], node: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    """Lines of code of ``node`` in the file's ``lines``: from its ``def`` to its end,
    without the docstring, blank lines and comment lines."""
    skip = set()
    first = node.body[0]
    if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) and isinstance(first.value.value, str):
        skip = set(range(first.lineno, first.end_lineno + 1))
    start = min([node.lineno] + [d.lineno for d in node.decorator_list])
    return sum(1 for i in range(start, node.end_lineno + 1)
               if i not in skip and lines[i - 1].strip() and not lines[i - 1].strip().startswith("#"))


def long_functions(root: Path, limit: int) -> list[str]:
    found = []
    for path in sorted(root.rglob("*.py")):
        text = path.read_text(encoding="utf-8")
        lines = text.splitlines()
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = code_lines(lines, node)
                if n > limit:
                    found.append(f"{path.relative_to(root.parent)}:{node.lineno} {node.name}: {n} lines")
    return found


def test_no_function_in_the_package_is_over_80_lines_of_code():
    found = long_functions(ROOT / "cnnps", MAX_FUNCTION_LINES)
    assert not found, f"functions over {MAX_FUNCTION_LINES} lines of code:\n" + "\n".join(found)


def test_the_prediction_api_is_argument_checking_and_orchestration():
    lines = (ROOT / "cnnps" / "api" / "prediction.py").read_text(encoding="utf-8").splitlines()
    assert len(lines) < MAX_PREDICTION_API_LINES, f"cnnps/api/prediction.py has {len(lines)} lines"


def test_the_counter_counts_code_not_docstrings_or_comments(tmp_path):
    pkg = tmp_path / "pkg"
    pkg.mkdir()
    body = "\n".join(f"    x{i} = {i}" for i in range(79))
    (pkg / "a.py").write_text(f'def short():\n    """Doc.\n\n    More doc.\n    """\n    # a comment\n\n{body}\n')
    assert long_functions(pkg, MAX_FUNCTION_LINES) == []  # def + 79 lines = 80
    (pkg / "b.py").write_text(f"def long():\n{body}\n    y = 1\n")
    assert long_functions(pkg, MAX_FUNCTION_LINES) == ["pkg/b.py:1 long: 81 lines"]
