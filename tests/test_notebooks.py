"""Notebooks tell the story and must run: each is executed top to bottom."""

import pathlib

import nbformat
from nbclient import NotebookClient

NOTEBOOKS = pathlib.Path(__file__).resolve().parents[1] / "notebooks"


def _execute(name: str) -> None:
    nb = nbformat.read(NOTEBOOKS / name, as_version=4)
    NotebookClient(nb, timeout=300, kernel_name="python3",
                   resources={"metadata": {"path": str(NOTEBOOKS)}}).execute()


def test_closed_loop_notebook_runs():
    _execute("closed_loop.ipynb")


def test_certified_perception_notebook_runs():
    _execute("certified_perception.ipynb")
