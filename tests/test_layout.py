"""The one-way layout of DESIGN 1, checked by walking every module's imports.

The folders systems/ and synthesis/ install as ``drake_cert.systems`` and ``drake_cert.synthesis``.

foundation (drake_cert/*.py) <- perception, certification  (never systems or synthesis)
foundation <- synthesis <- systems
cli and experiments may import from everywhere; nothing else imports them. No cycles.
``drake_cert/__init__.py`` is the public facade: it resolves its names lazily (PEP 562), so it
imports nothing at import time and is not part of the graph.
"""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("drake_cert", "systems", "synthesis")
# systems/ and synthesis/ install as drake_cert.systems and drake_cert.synthesis (pyproject.toml)
INSTALLED_AS = {"systems": "drake_cert.systems", "synthesis": "drake_cert.synthesis"}


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join([INSTALLED_AS.get(parts[0], parts[0]), *parts[1:]])


def all_modules() -> dict[str, Path]:
    return {module_name(p): p for pkg in PACKAGES for p in sorted((ROOT / pkg).rglob("*.py"))}


def imported_modules(path: Path, name: str, known: set[str]) -> set[str]:
    """Project modules imported anywhere in the file (module level or inside functions)."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        targets = []
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(package.split(".")[: len(package.split(".")) - node.level + 1]
                                + ([base] if base else []))
            subs = [f"{base}.{a.name}" for a in node.names]
            targets = [s for s in subs if s in known] or [base]
        for t in targets:
            while t and t not in known:
                t = t.rpartition(".")[0]
            if t and t != name:
                found.add(t)
    return found


def layer(module: str) -> str:
    parts = module.split(".")
    if len(parts) > 1 and parts[1] in ("perception", "certification", "experiments", "cli",
                                       "data", "systems", "synthesis"):
        return parts[1]
    return "foundation"


ALLOWED = {
    "foundation": {"foundation"},
    "data": {"foundation"},
    "perception": {"foundation", "perception"},
    "certification": {"foundation", "perception", "certification"},
    "synthesis": {"foundation", "synthesis"},
    "systems": {"foundation", "perception", "certification", "synthesis", "systems"},
    "experiments": {"foundation", "perception", "certification", "synthesis", "systems",
                    "experiments"},
    "cli": {"foundation", "perception", "certification", "synthesis", "systems", "experiments",
            "cli"},
}


def import_graph() -> dict[str, set[str]]:
    modules = all_modules()
    known = set(modules)
    graph = {name: imported_modules(path, name, known) for name, path in modules.items()
             if name != "drake_cert"}
    for deps in graph.values():
        deps.discard("drake_cert")
    return graph


def test_every_import_runs_one_way():
    violations = [f"{m} ({layer(m)}) imports {d} ({layer(d)})"
                  for m, deps in import_graph().items() for d in sorted(deps)
                  if layer(d) not in ALLOWED[layer(m)]]
    assert not violations, "\n".join(violations)


def test_the_facade_imports_nothing_at_import_time():
    tree = ast.parse((ROOT / "drake_cert" / "__init__.py").read_text())
    top_level_imports = [n for n in tree.body if isinstance(n, (ast.Import, ast.ImportFrom))
                         and not (isinstance(n, ast.ImportFrom) and n.module == "__future__")]
    assert top_level_imports == []


def test_there_are_no_import_cycles():
    graph = import_graph()
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m: str) -> None:
        state[m] = 1
        stack.append(m)
        for d in sorted(graph.get(m, ())):
            if state.get(d) == 1:
                pytest.fail("import cycle: " + " -> ".join(stack[stack.index(d):] + [d]))
            if d not in state:
                visit(d)
        stack.pop()
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m)


def test_the_rule_checker_catches_a_violation(tmp_path):
    bad = tmp_path / "bad.py"
    bad.write_text("def f():\n    from drake_cert.systems.plants import LinearLateralPlant\n")
    deps = imported_modules(bad, "drake_cert.certification.bad", set(all_modules()))
    assert "drake_cert.systems.plants" in deps
    assert layer("drake_cert.systems.plants") not in ALLOWED[layer("drake_cert.certification.bad")]


def test_nothing_imports_the_folders_by_their_bare_names():
    """``systems`` and ``synthesis`` are not import names (the wheel has neither): every import
    of them, in the package, tests, benchmarks and examples, goes through ``drake_cert``."""
    bare = []
    for folder in (*PACKAGES, "tests", "benchmarks", "examples"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text())):
                names = ([a.name for a in node.names] if isinstance(node, ast.Import) else
                         [node.module or ""] if isinstance(node, ast.ImportFrom)
                         and node.level == 0 else [])
                bare += [f"{path.relative_to(ROOT)}: {n}" for n in names
                         if n.split(".")[0] in INSTALLED_AS]
    assert not bare, "\n".join(bare)
