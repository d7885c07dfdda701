"""Atomic writes and provenance for saved artefacts (designs, models, results)."""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from datetime import UTC, datetime
from pathlib import Path

SCHEMA_VERSION = 1


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically: a temporary file in the same folder, fsync, rename.

    A reader never sees a half-written file; an interrupted write leaves the old file intact.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp creates 0600; saved artefacts are shareable
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


def check_writable(path: str | os.PathLike, option: str = "output") -> Path:
    """Raise :class:`ConfigError` unless :func:`atomic_write_bytes` can write ``path``.

    Called before the work that makes the file, so a bad path fails in one line and leaves
    nothing behind: ``path`` must not be a folder, its nearest existing ancestor must be a
    folder (not a regular file) in which this process can create a file (folders in between
    are made). That is tried, with a nameless temporary file, rather than read off the
    permission bits: root passes every permission check yet cannot write in ``/proc``, a
    read-only mount or some network folders.
    ``option`` names the command-line option in the message.
    """
    from drake_cert.errors import ConfigError

    path = Path(path)
    if path.is_dir():
        raise ConfigError(f"{option} {path}: is a folder; give a file name")
    ancestor = path.parent
    while not ancestor.exists() and ancestor != ancestor.parent:
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise ConfigError(f"{option} {path}: {ancestor} is a file, not a folder")
    try:
        with tempfile.TemporaryFile(dir=ancestor):
            pass
    except OSError as e:
        raise ConfigError(f"{option} {path}: folder {ancestor} is not writable (creating a "
                          f"file there failed: {e.strerror or e})") from None
    return path


def check_writable_folder(path: str | os.PathLike, option: str = "folder") -> Path:
    """Raise :class:`ConfigError` unless files can be written in the folder ``path`` (made
    if missing): it must not be a regular file, and its nearest existing ancestor must be a
    writable folder (:func:`check_writable`). Called before the work that fills it."""
    from drake_cert.errors import ConfigError

    path = Path(path)
    if path.exists() and not path.is_dir():
        raise ConfigError(f"{option} {path}: is a file; give a folder")
    check_writable(path / ".drake-cert-probe", option)
    return path


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    return atomic_write_bytes(path, text.encode("utf-8"))


def git_revision() -> str:
    """The git revision of the source tree this package runs from, or 'unknown'."""
    here = Path(__file__).resolve().parent
    try:
        out = subprocess.run(
            ["git", "-C", str(here), "rev-parse", "--short", "HEAD"],
            capture_output=True, text=True, timeout=5, check=False,
        )
        rev = out.stdout.strip()
        if not rev:
            return "unknown"
        dirty = subprocess.run(
            ["git", "-C", str(here), "status", "--porcelain", "--untracked-files=no"],
            capture_output=True, text=True, timeout=5, check=False,
        ).stdout.strip()
        return rev + ("-dirty" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def provenance(seed: int | None = None, command: list[str] | None = None) -> dict:
    """Provenance block stored with every artefact: command line, git revision, seed, time.

    The program's own path is reduced to its name (``drake-cert``, not the absolute path of
    the virtual environment that ran it): artefacts are read on other machines.
    """
    words = list(command if command is not None else sys.argv)
    if words:
        words[0] = os.path.basename(words[0]) or words[0]
    return {
        "schema_version": SCHEMA_VERSION,
        "command": " ".join(words),
        "git_revision": git_revision(),
        "seed": seed,
        "created_utc": datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
    }
