"""The README's ten-line example of the public API runs as printed, and the facade stays light."""

import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def readme_example() -> str:
    text = (ROOT / "README.md").read_text()
    marker = text.index("<!-- api-example")
    match = re.search(r"```python\n(.*?)```", text[marker:], re.S)
    return match.group(1)


def test_the_readme_example_runs_and_reports_a_car_in_its_lane():
    code = readme_example()
    assert len(code.strip().splitlines()) <= 12
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=ROOT, timeout=300)
    assert out.returncode == 0, out.stderr
    assert "left the lane: False" in out.stdout


def test_the_usage_example_builds_and_drives_the_certified_diagram():
    text = (ROOT / "docs/usage.md").read_text()
    marker = text.index("<!-- api-example: the certified Diagram")
    code = re.search(r"```python\n(.*?)```", text[marker:], re.S).group(1)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=ROOT, timeout=600)
    assert out.returncode == 0, out.stderr
    assert "'perception'" in out.stdout and "'controller'" in out.stdout
    assert "unprotected 0.00 s" in out.stdout
    bound = float(re.search(r"guarantee_failure_bound ([0-9.]+)", out.stdout).group(1))
    assert 0.0 < bound <= 0.01


def test_importing_the_facade_imports_neither_torch_nor_pydrake():
    code = "import sys, drake_cert; print('torch' in sys.modules, 'pydrake' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.stdout.split() == ["False", "False"]


def test_every_public_name_resolves():
    import drake_cert

    for name in drake_cert.__all__:
        assert getattr(drake_cert, name) is not None, name


def test_verify_design_table_in_the_facade_reads_files_and_returns_a_typed_report(
        default_design_table, tmp_path):
    import dataclasses

    import drake_cert as dc
    from drake_cert.config import default_path

    snow = [d for d in default_design_table.designs if d.labels == ["snow"]]
    path = tmp_path / "snow.yaml"
    dc.save_design_table(path, dataclasses.replace(default_design_table, designs=snow),
                         switching=False)
    report = dc.verify_design_table(path)
    assert isinstance(report, dc.VerificationReport) and dataclasses.is_dataclass(report)
    assert report.ok and report.verdict == "pass" and not report.completeness_checked
    (design,) = report.designs
    assert design.label_range == "snow" and design.interval_n_per_rad == snow[0].interval
    # against the shipped conditions (a path) the one-design table is incomplete
    report = dc.verify_design_table(path, conditions=default_path("conditions.yaml"))
    assert not report.ok and report.designs[0].ok and len(report.missing) == 19
    assert report.to_dict()["completeness"]["holds"] is False


def test_verify_design_table_raises_the_typed_error_for_an_unreadable_file(tmp_path):
    import pytest

    import drake_cert as dc

    with pytest.raises(dc.DesignFormatError, match="cannot read file"):
        dc.verify_design_table(tmp_path / "missing.yaml")
    (tmp_path / "bad.yaml").write_text("designs: [unclosed\n")
    with pytest.raises(dc.DesignFormatError, match="not valid YAML"):
        dc.verify_design_table(tmp_path / "bad.yaml")
