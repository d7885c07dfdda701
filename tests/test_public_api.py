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


def test_importing_the_facade_imports_neither_torch_nor_pydrake():
    code = "import sys, drake_cert; print('torch' in sys.modules, 'pydrake' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.stdout.split() == ["False", "False"]


def test_every_public_name_resolves():
    import drake_cert

    for name in drake_cert.__all__:
        assert getattr(drake_cert, name) is not None, name
