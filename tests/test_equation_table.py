"""The equations table of the design notes (section 10, columns equation / claim, implemented
in, checked by) stays true: every function it names imports, and every test it names exists.

Reading rules (the table's own shorthand): in "implemented in", a bare name after a dotted
path lives in the module of the previous dotted name; in "checked by", ``test_x.py`` means
``tests/test_x.py`` and a bare ``test_name`` lives in the previous file.
"""

import ast
import importlib
import re
from functools import cache
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
HEADER = "| equation / claim | implemented in | checked by |"


def table_rows() -> list[tuple[str, str, str]]:
    lines = (ROOT / "docs" / "design.md").read_text().splitlines()
    start = lines.index(HEADER) + 2  # skip the header and the |---| line
    rows = []
    for line in lines[start:]:
        if not line.startswith("|"):
            break
        cells = split_cells(line)
        rows.append((cells[0], cells[1], cells[2]))
    return rows


def split_cells(line: str) -> list[str]:
    """A Markdown table row's cells; a "|" inside backticks or escaped as "\\|" stays."""
    cells, current, code, i = [], "", False, 0
    text = line.strip()
    while i < len(text):
        ch = text[i]
        if ch == "\\" and i + 1 < len(text) and text[i + 1] == "|":
            current += "|"
            i += 2
            continue
        if ch == "`":
            code = not code
        if ch == "|" and not code:
            cells.append(current.strip())
            current = ""
        else:
            current += ch
        i += 1
    return cells[1:]


def backticked(cell: str) -> list[str]:
    return re.findall(r"`([^`]+)`", cell)


def resolve(dotted: str):
    """The object a dotted path names (longest importable module prefix, then attributes)."""
    parts = dotted.split(".")
    for i in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:i]))
        except ModuleNotFoundError:
            continue
        for name in parts[i:]:
            obj = getattr(obj, name)
        return obj
    raise ModuleNotFoundError(dotted)


def function_names(cell: str) -> list[str]:
    """Full dotted names of the "implemented in" cell, bare names completed from the last."""
    names, module = [], None
    for item in backticked(cell):
        if "." in item:
            obj = resolve(item)
            module = obj.__name__ if hasattr(obj, "__path__") or type(obj).__name__ == "module" \
                else obj.__module__
            names.append(item)
        elif module is not None:
            names.append(f"{module}.{item}")
        else:
            names.append(item)
    return names


@cache
def functions_in_file(path: Path) -> frozenset[str]:
    tree = ast.parse(path.read_text())
    return frozenset(n.name for n in ast.walk(tree)
                     if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef)))


def named_tests(cell: str) -> list[tuple[Path, str | None]]:
    """(file, test function or None) for each test the "checked by" cell names."""
    refs, current = [], None
    for item in backticked(cell):
        file_part, _, func = item.partition("::")
        if file_part.endswith(".py"):
            current = ROOT / (file_part if file_part.startswith("tests/") else
                              f"tests/{file_part}")
            refs.append((current, func or None))
        elif item.startswith("test_") and current is not None:
            refs.append((current, item))
    return refs


ROWS = table_rows()


def test_the_table_is_found_and_has_rows():
    assert len(ROWS) >= 20


@pytest.mark.parametrize("claim, functions, tests", ROWS, ids=[r[0][:40] for r in ROWS])
def test_every_function_and_test_of_the_row_exists(claim, functions, tests):
    missing = []
    for name in function_names(functions):
        try:
            resolve(name)
        except (ImportError, AttributeError) as e:
            missing.append(f"function {name}: {type(e).__name__}: {e}")
    refs = named_tests(tests)
    if not refs:
        missing.append(f"no test named in {tests!r}")
    for path, func in refs:
        if not path.exists():
            missing.append(f"test file {path.relative_to(ROOT)} does not exist")
        elif func is not None and func not in functions_in_file(path):
            missing.append(f"test {path.relative_to(ROOT)}::{func} does not exist")
    assert not missing, f"design.md table row {claim!r}: " + "; ".join(missing)
