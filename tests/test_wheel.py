"""The installed package is one namespace: systems/ and synthesis/ install as
``drake_cert.systems`` and ``drake_cert.synthesis``, and a non-editable install works on its own.

The wheel is built from this checkout without build isolation (no network). The fresh
environment sees this environment's third-party packages through a path file, but not its
editable finder, so every ``drake_cert`` module it imports comes from the installed wheel.
"""

import shutil
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest
from test_public_api import readme_example

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    # built from a copy of what the wheel holds, so that setuptools' build/ stays out of the tree
    source = tmp_path_factory.mktemp("source")
    shutil.copy(ROOT / "pyproject.toml", source)
    for folder in ("drake_cert", "systems", "synthesis"):
        shutil.copytree(ROOT / folder, source / folder,
                        ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    out = tmp_path_factory.mktemp("wheel")
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps",
                    "--no-build-isolation", "--wheel-dir", str(out), str(source)],
                   check=True, capture_output=True, timeout=300)
    (path,) = out.glob("drake_cert-*.whl")
    return path


@pytest.fixture(scope="module")
def fresh_install(wheel, tmp_path_factory) -> Path:
    """A new virtual environment with the wheel installed non-editable; returns its bin/."""
    env = tmp_path_factory.mktemp("env")
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(env)], check=True,
                   timeout=120)
    python = env / "bin" / "python"
    purelib = subprocess.run([str(python), "-c", "import sysconfig; "
                              "print(sysconfig.get_paths()['purelib'])"],
                             capture_output=True, text=True, check=True).stdout.strip()
    Path(purelib, "third_party.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    subprocess.run([sys.executable, "-m", "pip", "--python", str(python), "install", "--quiet",
                    "--no-deps", str(wheel)], check=True, capture_output=True, timeout=300)
    return env / "bin"


def test_the_wheel_holds_systems_and_synthesis_inside_drake_cert(wheel):
    names = zipfile.ZipFile(wheel).namelist()
    top = {n.split("/")[0] for n in names if not n.split("/")[0].endswith(".dist-info")}
    assert top == {"drake_cert"}
    assert "drake_cert/systems/driving.py" in names
    assert "drake_cert/synthesis/table.py" in names


@pytest.mark.slow  # a fresh environment: ~7 s; the wheel's contents are checked fast above
def test_a_non_editable_install_runs_the_cli_and_imports_from_itself(fresh_install, tmp_path):
    help_ = subprocess.run([str(fresh_install / "drake-cert"), "--help"], capture_output=True,
                           text=True, cwd=tmp_path, timeout=120)
    assert help_.returncode == 0, help_.stderr
    assert "synthesize" in help_.stdout
    where = subprocess.run(
        [str(fresh_install / "python"), "-c",
         "import importlib.util as u, drake_cert.systems.driving as d, drake_cert.synthesis as s;"
         "print(d.__file__); print(s.__file__);"
         "print(u.find_spec('systems'), u.find_spec('synthesis'))"],
        capture_output=True, text=True, cwd=tmp_path, timeout=120)
    assert where.returncode == 0, where.stderr
    driving, synthesis, top_level = where.stdout.splitlines()
    assert driving.startswith(str(fresh_install.parent)) and "site-packages" in driving
    assert synthesis.startswith(str(fresh_install.parent))
    assert top_level == "None None"


@pytest.mark.slow
def test_the_readme_example_runs_from_a_non_editable_install(fresh_install, tmp_path):
    out = subprocess.run([str(fresh_install / "python"), "-c", readme_example()],
                         capture_output=True, text=True, cwd=tmp_path, timeout=600)
    assert out.returncode == 0, out.stderr
    assert "left the lane: False" in out.stdout
