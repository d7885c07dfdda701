"""Functions take a few named things and systems' constructors only declare (STYLE: a frozen
parameter object per concept, as Drake's ``AcrobotParams``; validation and precomputation in
functions of their own)."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("drake_cert", "systems", "synthesis")
MOST_PARAMETERS = 8        # no function takes more
MANY_PARAMETERS = 6        # and at most MANY_ALLOWED take more than this
MANY_ALLOWED = 15
CONSTRUCTOR_LINES = 30     # a LeafSystem's or Diagram's __init__, signature included


def _functions():
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    yield path.relative_to(ROOT), node


def parameter_count(node: ast.FunctionDef) -> int:
    """Named parameters, ``self`` and ``cls`` not counted (``*args``/``**kwargs`` neither)."""
    a = node.args
    names = [p.arg for p in (*a.posonlyargs, *a.args, *a.kwonlyargs)]
    return len(names) - (1 if names and names[0] in ("self", "cls") else 0)


def test_functions_take_at_most_eight_things_and_few_take_more_than_six():
    counts = {f"{path}:{node.name}": parameter_count(node) for path, node in _functions()}
    too_many = {k: v for k, v in counts.items() if v > MOST_PARAMETERS}
    many = sorted(k for k, v in counts.items() if v > MANY_PARAMETERS)
    assert not too_many, too_many
    assert len(many) <= MANY_ALLOWED, many


def test_system_constructors_only_declare():
    long = []
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            for cls in ast.walk(ast.parse(path.read_text())):
                if not isinstance(cls, ast.ClassDef):
                    continue
                bases = {ast.unparse(b).rpartition(".")[2] for b in cls.bases}
                if not bases & {"LeafSystem", "Diagram", "_NamedInputPlant"}:
                    continue
                for node in cls.body:
                    if isinstance(node, ast.FunctionDef) and node.name == "__init__":
                        lines = node.end_lineno - node.lineno + 1
                        if lines > CONSTRUCTOR_LINES:
                            long.append(f"{path.relative_to(ROOT)}:{cls.name} {lines} lines")
    assert not long, long


def test_the_counter_counts_what_a_caller_passes():
    tree = ast.parse("class A:\n def f(self, a, b, *c, d, e=1, **k): pass\n"
                     "def g(a, /, b): pass\n")
    f, g = sorted((n for n in ast.walk(tree) if isinstance(n, ast.FunctionDef)),
                  key=lambda n: n.name)
    assert parameter_count(f) == 4 and parameter_count(g) == 2
