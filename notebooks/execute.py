"""Execute the notebooks top to bottom at their full settings and store them with outputs.

``make notebooks`` runs this. Each notebook runs in a fresh kernel in ``notebooks/`` with
``DRAKE_CERT_PRECISION=fp32`` (the arithmetic every CPU has, so the stored outputs do not
depend on whether the machine that made them has native bfloat16) and without
``DRAKE_CERT_NOTEBOOK_QUICK`` (the tests set that one for small settings). Execution
timestamps are dropped, so re-running on unchanged code changes only what the code prints.
A notebook whose outputs contain a path of this machine (the checkout's absolute path or
the home folder) is refused: outputs are read on the repository page by people on other
machines. Files are replaced atomically.

Usage: ``python notebooks/execute.py [NAME.ipynb ...]`` (default: every notebook here).
"""

from __future__ import annotations

import os
import pathlib
import sys
import tempfile
import time

import nbformat
from nbclient import NotebookClient

HERE = pathlib.Path(__file__).resolve().parent
ROOT = HERE.parent


def machine_paths() -> list[str]:
    """Absolute paths of this machine that must not appear in a stored output."""
    paths = {str(ROOT), str(pathlib.Path.home())}
    return sorted(p for p in paths if len(p) > 1)


def output_texts(nb) -> list[str]:
    """Every text of every output (stream text, text/plain, text/html, error tracebacks)."""
    texts = []
    for cell in nb.cells:
        for out in cell.get("outputs", []):
            if "text" in out:
                texts.append(out["text"])
            for mime, value in out.get("data", {}).items():
                if mime.startswith("text/"):
                    texts.append(value if isinstance(value, str) else "".join(value))
            texts.extend(out.get("traceback", []))
    return texts


def paths_in_outputs(nb) -> list[str]:
    """The machine paths found in the notebook's outputs (empty when it is clean)."""
    return [p for p in machine_paths() if any(p in t for t in output_texts(nb))]


def strip_timings(nb) -> None:
    """Drop the per-cell execution timestamps nbclient records (they change every run)."""
    for cell in nb.cells:
        cell.get("metadata", {}).pop("execution", None)


def execute(path: pathlib.Path, timeout_s: int = 1800) -> float:
    """Run one notebook in place; returns its wall time in seconds."""
    nb = nbformat.read(path, as_version=4)
    env_before = {k: os.environ.get(k) for k in ("DRAKE_CERT_PRECISION",
                                                 "DRAKE_CERT_NOTEBOOK_QUICK")}
    os.environ["DRAKE_CERT_PRECISION"] = "fp32"
    os.environ.pop("DRAKE_CERT_NOTEBOOK_QUICK", None)
    start = time.perf_counter()
    try:
        NotebookClient(nb, timeout=timeout_s, kernel_name="python3",
                       resources={"metadata": {"path": str(path.parent)}}).execute()
    finally:
        for k, v in env_before.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    wall = time.perf_counter() - start
    strip_timings(nb)
    found = paths_in_outputs(nb)
    if found:
        raise SystemExit(f"{path.name}: outputs contain this machine's path(s) {found}; "
                         "print paths relative to the repository")
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".ipynb.tmp")
    with os.fdopen(fd, "w", encoding="utf-8") as f:
        nbformat.write(nb, f)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    return wall


def main(argv: list[str]) -> int:
    names = argv or sorted(p.name for p in HERE.glob("*.ipynb"))
    for name in names:
        path = HERE / name
        if not path.is_file():
            print(f"notebooks/execute.py: no notebook {name} in notebooks/", file=sys.stderr)
            return 2
        print(f"{name} ...", flush=True)
        print(f"{name}: {execute(path):.0f} s", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
