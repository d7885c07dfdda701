"""Notebooks tell the story and must run: each is executed top to bottom."""

import pathlib

import nbformat
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


def test_certified_perception_notebook_runs(monkeypatch):
    _execute("certified_perception.ipynb", monkeypatch)


def test_certified_driving_notebook_runs(monkeypatch):
    _execute("certified_driving.ipynb", monkeypatch)


def test_reproduction_notebook_runs(monkeypatch):
    _execute("reproduction.ipynb", monkeypatch)
