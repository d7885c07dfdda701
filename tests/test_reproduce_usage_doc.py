"""docs/usage.md says what `drake-cert reproduce` prints: every key of its one JSON line, and
`paper_claims` as a count per verdict class (one verdict per claim at the paper's budget)."""

import ast
from pathlib import Path

from drake_cert.experiments import paper_claims

ROOT = Path(__file__).resolve().parents[1]


def printed_keys() -> list[str]:
    """The keys of the JSON line that ``_write_reproduction`` prints, read from its source."""
    tree = ast.parse((ROOT / "drake_cert/cli/reproduce.py").read_text())
    func = next(n for n in ast.walk(tree)
                if isinstance(n, ast.FunctionDef) and n.name == "_write_reproduction")
    dumped = next(n.args[0] for n in ast.walk(func) if isinstance(n, ast.Call)
                  and isinstance(n.func, ast.Attribute) and n.func.attr == "dumps"
                  and isinstance(n.args[0], ast.Dict))
    return [k.value for k in dumped.keys]


def reproduce_row() -> str:
    text = (ROOT / "docs/usage.md").read_text()
    return next(line for line in text.splitlines()
                if line.startswith("| [`drake-cert reproduce`]"))


def test_usage_names_every_key_the_reproduction_prints():
    printed = reproduce_row().split("prints one JSON line:")[1]
    keys = printed_keys()
    assert "paper_claims" in keys and "paper_claims_failing" in keys
    for key in keys:
        assert f"`{key}`" in printed, key


def test_usage_describes_paper_claims_as_a_count_per_verdict_at_the_papers_budget():
    printed = reproduce_row().split("prints one JSON line:")[1]
    assert "how many hold, fail, were not tested" not in printed
    assert "one verdict per claim at the paper's budget eps = 1" in printed
    for verdict in paper_claims.VERDICTS:
        assert f"`{verdict}`" in printed, verdict
    counts = paper_claims.verdict_counts([])
    assert list(counts) == list(paper_claims.VERDICTS)  # every class, zeros included
