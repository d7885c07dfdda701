"""The reproduction's store: finished frames and calibrations on disk, each reused only by a
run with the same identity (settings, model and data hashes, design table), so that a stopped
run resumes where it stopped.
"""

from __future__ import annotations

import dataclasses

from drake_cert.experiments.reproduce_config import FrameTask, ReproduceConfig


def model_files(config: ReproduceConfig) -> list[tuple[str, str, float]]:
    """(preset, task, sigma) of every model the run evaluates."""
    sigmas = sorted({0.0, *config.sigmas, config.sweep_sigma})
    out = [(p, "classify", s) for p in config.presets for s in sigmas]
    if config.regression:
        out += [(p, "regress", s) for p in config.presets for s in sorted({0.0, *config.sigmas})]
    return out


def run_identity(config: ReproduceConfig, designs: list) -> str:
    """What a stored frame must have been made with to be reused: every setting but the
    frame count (the first k frames of a preset do not depend on it), the SHA-256 of every
    model file, of the data tables (vehicle, settings, conditions) and of the design table
    (rounded to 6 significant digits). A SHA-256 hex digest."""
    import hashlib
    import json
    from pathlib import Path

    from drake_cert.perception.models import file_sha256, model_path

    settings = dataclasses.asdict(config)
    settings.pop("frames")

    def rounded(x):
        if isinstance(x, float):
            return float(f"{x:.6g}")
        if isinstance(x, dict):
            return {k: rounded(v) for k, v in sorted(x.items())}
        if isinstance(x, list | tuple):
            return [rounded(v) for v in x]
        return x

    data = Path(__file__).resolve().parents[1] / "data"
    blob = dict(
        settings=rounded(settings),
        models={f"{p}/{t}/{s}": file_sha256(model_path(p, t, s))
                for p, t, s in model_files(config)},
        data={f.name: file_sha256(f) for f in sorted(data.glob("*.yaml"))},
        designs=rounded([dataclasses.asdict(d) for d in designs]),
    )
    text = json.dumps(blob, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()


class RunStore:
    """What a reproduction has finished, under ``root``: one JSON file per frame (its rows),
    ``calibration.json`` (the h betas) and ``conformal.json`` (g's robust conformal
    calibrations), each written atomically as it arrives and reused only by a run with the same
    :func:`run_identity`. A stopped run resumes where it stopped."""

    def __init__(self, root):
        from pathlib import Path

        from drake_cert.io import git_revision

        self.root = Path(root)
        self.revision = git_revision()

    def _frame_path(self, task: FrameTask):
        return self.root / task.preset / f"frame-{task.position:04d}.json"

    def _read(self, path, identity: str):
        import json

        if not path.exists():
            return None
        try:
            stored = json.loads(path.read_text())
        except (OSError, ValueError):
            return None  # unreadable: recompute
        return stored if stored.get("identity") == identity else None

    def frame(self, identity: str, task: FrameTask) -> list[dict] | None:
        stored = self._read(self._frame_path(task), identity)
        return None if stored is None else stored["rows"]

    def put_frame(self, identity: str, task: FrameTask, rows: list[dict]) -> None:
        self._write(self._frame_path(task), identity, rows=rows)

    def betas(self, identity: str) -> dict:
        stored = self._read(self.root / "calibration.json", identity)
        if stored is None:
            return {}
        return {(p, float(s)): float(b) for p, s, b in stored["betas"]}

    def put_betas(self, identity: str, betas: dict) -> None:
        self._write(self.root / "calibration.json", identity,
                    betas=[[p, s, b] for (p, s), b in sorted(betas.items())])

    def conformal(self, identity: str) -> dict:
        from drake_cert.certification.conformal import RobustConformalCalibration

        stored = self._read(self.root / "conformal.json", identity)
        if stored is None:
            return {}
        return {(p, float(s)): RobustConformalCalibration.from_json(c)
                for p, s, c in stored["calibrations"]}

    def put_conformal(self, identity: str, calibrations: dict) -> None:
        self._write(self.root / "conformal.json", identity,
                    calibrations=[[p, s, c.to_json()] for (p, s), c in
                                  sorted(calibrations.items())])

    def _write(self, path, identity: str, **content) -> None:
        import json

        from drake_cert.io import atomic_write_text

        text = json.dumps(dict(identity=identity, git_revision=self.revision, **content),
                          separators=(",", ":"))
        atomic_write_text(path, text + "\n")
