"""Notebooks tell the story and must run: each is executed top to bottom."""

import pathlib

import nbformat
import pytest
from nbclient import NotebookClient

NOTEBOOKS = pathlib.Path(__file__).resolve().parents[1] / "notebooks"


def _execute(name: str, monkeypatch) -> None:
    # Small settings: the notebooks read this and shrink their work (the kernel inherits the
    # environment of this process; monkeypatch restores it afterwards).
    monkeypatch.setenv("DRAKE_CERT_NOTEBOOK_QUICK", "1")
    nb = nbformat.read(NOTEBOOKS / name, as_version=4)
    NotebookClient(nb, timeout=300, kernel_name="python3",
                   resources={"metadata": {"path": str(NOTEBOOKS)}}).execute()


def test_closed_loop_notebook_runs(monkeypatch):
    _execute("closed_loop.ipynb", monkeypatch)


@pytest.mark.slow  # ~30 s on 2 cores
def test_certified_perception_notebook_runs(monkeypatch):
    _execute("certified_perception.ipynb", monkeypatch)


@pytest.mark.slow  # ~60 s on 2 cores; the Diagram it drives is tested fast in test_driving.py
def test_certified_driving_notebook_runs(monkeypatch):
    _execute("certified_driving.ipynb", monkeypatch)


@pytest.mark.slow  # ~65 s on 2 cores
def test_reproduction_notebook_runs(monkeypatch):
    _execute("reproduction.ipynb", monkeypatch)


def test_committed_notebooks_show_their_outputs_and_no_machine_path():
    """A reader on the repository page sees every notebook's printed results and plots
    (`make notebooks` stores them), and no output names a folder of the machine that ran it."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("execute", NOTEBOOKS / "execute.py")
    execute = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(execute)
    for path in sorted(NOTEBOOKS.glob("*.ipynb")):
        nb = nbformat.read(path, as_version=4)
        code = [c for c in nb.cells if c.cell_type == "code"]
        assert all(c.get("execution_count") for c in code), f"{path.name}: a cell never ran"
        assert not any(o.get("output_type") == "error" for c in code for o in c.outputs), \
            f"{path.name}: stored with an error"
        images = [o for c in code for o in c.outputs if "image/png" in o.get("data", {})]
        assert images, f"{path.name}: no plot stored"
        assert execute.paths_in_outputs(nb) == [], path.name
