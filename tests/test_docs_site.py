"""The documentation site builds strict (a broken link or reference fails) with an API reference
that covers every module of the library (README, docs/index.md; `make docs`)."""

import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("drake_cert/certification", "drake_cert/perception", "drake_cert/experiments",
            "systems", "synthesis")
TOP_MODULES = ("config", "errors", "io", "rng", "progress", "threads", "metrics", "dynamics")


def _documented() -> set[str]:
    text = "\n".join(p.read_text() for p in (ROOT / "docs/api").glob("*.md"))
    return set(re.findall(r"^::: ([\w.]+)$", text, flags=re.M))


def test_the_api_reference_names_every_module_of_the_library():
    expected = {f"{folder.replace('/', '.')}.{f.stem}" for folder in PACKAGES
                for f in (ROOT / folder).glob("*.py") if f.name != "__init__.py"}
    expected |= {f"drake_cert.{m}" for m in TOP_MODULES}
    assert expected - _documented() == set()
    assert _documented() - expected == set()  # nothing listed that does not exist


def test_make_docs_builds_the_site_strict_with_the_api_reference(tmp_path):
    site = tmp_path / "site"
    run = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir",
                          str(site)], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
    systems = (site / "api/systems/index.html").read_text()
    assert 'id="systems.driving.drive"' in systems  # a function's entry, from its docstring
    assert "guarantee_failure_bound" in systems
    synthesis = (site / "api/synthesis/index.html").read_text()
    assert 'id="synthesis.speed.search_speed"' in synthesis
    # docs/results.md links the committed run outside docs/: those pages join the site
    assert (site / "results/paper/index.html").exists()  # its README.md
    assert (site / "search/search_index.json").exists()
