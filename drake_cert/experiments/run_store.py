"""The reproduction's store: finished frames and calibrations on disk, each reused only by a
run with the same identity (settings, model and data hashes, design table), so that a stopped
run resumes where it stopped, on this machine or another.

Portable identity. The design table is synthesized on the machine that runs, and its floats
(LMI gains, margins) move in their last digits from one CPU or BLAS to another. No rounding of
a float makes a hash both blind to every such move and sensitive to a real change (some value
always sits on a rounding boundary), so the identity does not hash this machine's digits: the
store keeps the full design table each identity was made with (``identity.json``), and a
design table that equals a stored one within ``DESIGN_RTOL`` (relative, plus ``DESIGN_ATOL``)
in every float, with the same labels and conditions, is hashed as that stored table
(:func:`canonical_designs`). The tolerance is the SDP solver's, not the machine's last digits:
an interior-point solve lands elsewhere within its own tolerance on another CPU (gains and
margins moved by up to 5.3e-5 relative between an AMD EPYC and an Intel Xeon). A real change
(a safe speed in its 4th digit, 5e-4 relative) is outside it and makes a new identity.

Arithmetic. The precision (fp32 or bf16) is part of the identity: it changes the numbers.
Whether bf16 ran natively (AVX512-BF16 or AMX) or emulated is not, but it changes the last
digits too, so a store is not finished in the other kind of bf16 (:meth:`RunStore.check_arithmetic`
refuses, saying so); rewriting its tables (``--from-store``) computes nothing and works
anywhere. The CPU, its flags and torch's version are recorded beside every frame, as metadata.

Cost. ``cpu.json`` is a ledger of the workers' CPU seconds per identity and stage, added as each
calibration and frame is stored, so a run's cost survives the invocations that made it.
"""

from __future__ import annotations

import dataclasses
import math

from drake_cert.errors import ConfigError
from drake_cert.experiments.reproduce_config import FrameTask, ReproduceConfig

# relative tolerance of "the same design table": Clarabel's solves of the same LMIs differ by up
# to 5.3e-5 relative from one CPU to another (measured 2026-11-28, AMD EPYC vs Intel Xeon: the
# L1-condition margin of a rain design; gains k_m up to 9.3e-6), with the same safe speeds
DESIGN_RTOL = 1e-4
DESIGN_ATOL = 1e-9  # absolute floor, for margins near 0
MANIFEST = "identity.json"
CPU_LEDGER = "cpu.json"  # the workers' CPU seconds per stage and identity, as parts are stored


def model_files(config: ReproduceConfig) -> list[tuple[str, str, float]]:
    """(preset, task, sigma) of every model the run evaluates."""
    sigmas = sorted({0.0, *config.sigmas, config.sweep_sigma})
    out = [(p, "classify", s) for p in config.presets for s in sigmas]
    if config.regression:
        out += [(p, "regress", s) for p in config.presets for s in sorted({0.0, *config.sigmas})]
    return out


def design_dicts(designs: list) -> list[dict]:
    """The design table as JSON-ready dicts (what the identity and the manifest hold)."""
    return [d if isinstance(d, dict) else dataclasses.asdict(d) for d in designs]


def same_design_table(a: list[dict], b: list[dict], rtol: float = DESIGN_RTOL,
                      atol: float = DESIGN_ATOL) -> str:
    """Why two design tables (:func:`design_dicts`) differ, or "" when they are the same
    design table: the same structure, strings and booleans, and every float within
    ``atol + rtol * max(|x|, |y|)``."""
    def first_difference(x, y, where: str) -> str:
        if isinstance(x, bool) or isinstance(y, bool) or isinstance(x, str) or x is None:
            return "" if x == y else f"{where}: {x!r} vs {y!r}"
        if isinstance(x, int | float) and isinstance(y, int | float):
            x, y = float(x), float(y)
            if x == y or (math.isfinite(x) and math.isfinite(y)
                          and abs(x - y) <= atol + rtol * max(abs(x), abs(y))):
                return ""
            return f"{where}: {x!r} vs {y!r}"
        if isinstance(x, dict) and isinstance(y, dict):
            if sorted(x) != sorted(y):
                return f"{where}: fields {sorted(x)} vs {sorted(y)}"
            return next((w for k in sorted(x)
                         if (w := first_difference(x[k], y[k], f"{where}.{k}"))), "")
        if isinstance(x, list | tuple) and isinstance(y, list | tuple):
            if len(x) != len(y):
                return f"{where}: {len(x)} vs {len(y)} entries"
            return next((w for i, (u, v) in enumerate(zip(x, y, strict=True))
                         if (w := first_difference(u, v, f"{where}[{i}]"))), "")
        return "" if x == y else f"{where}: {x!r} vs {y!r}"

    if len(a) != len(b):
        return f"{len(a)} designs vs {len(b)}"
    for da, db in zip(a, b, strict=True):
        name = "+".join(da.get("labels") or []) or "regression design"
        why = first_difference(da, db, f"design {name}")
        if why:
            return why
    return ""


def canonical_designs(designs: list, references: list[list[dict]] = ()) -> list[dict]:
    """The design table the identity hashes: the first of ``references`` (tables a store
    holds) that is the same design table (:func:`same_design_table`), else ``designs``."""
    table = design_dicts(designs)
    return next((ref for ref in references if not same_design_table(table, ref)), table)


def identity_parts(config: ReproduceConfig, designs: list,
                   references: list[list[dict]] = ()) -> dict:
    """What a stored frame must have been made with to be reused: every setting but the frame
    count (the first k frames of a preset do not depend on it), the SHA-256 of every model
    file and of the data tables (vehicle, settings, conditions), and the design table
    (:func:`canonical_designs`)."""
    from pathlib import Path

    from drake_cert.perception.models import file_sha256, model_path

    settings = dataclasses.asdict(config)
    settings.pop("frames")
    data = Path(__file__).resolve().parents[1] / "data"
    return dict(
        settings=settings,
        models={f"{p}/{t}/{s}": file_sha256(model_path(p, t, s))
                for p, t, s in model_files(config)},
        data={f.name: file_sha256(f) for f in sorted(data.glob("*.yaml"))},
        designs=canonical_designs(designs, references),
    )


def identity_of(parts: dict) -> str:
    """The SHA-256 hex digest of :func:`identity_parts` (floats as Python writes them)."""
    import hashlib
    import json

    text = json.dumps(parts, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()


def run_identity(config: ReproduceConfig, designs: list,
                 references: list[list[dict]] = ()) -> str:
    """The identity of a run with ``config`` and ``designs`` (``references``: the design
    tables a store holds; see the module doc). A SHA-256 hex digest."""
    return identity_of(identity_parts(config, designs, references))


def arithmetic(precision: str) -> dict:
    """How this machine evaluates the models in ``precision``: ``numbers`` says what changes
    the digits ("fp32", "bf16-native" or "bf16-emulated"); the CPU, its vector flags and
    torch's version are metadata."""
    import platform

    import torch

    from drake_cert.certification.sampler import bf16_supported

    cpu, flags = platform.processor() or platform.machine(), set()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name") and ":" in line:
                    cpu = line.split(":", 1)[1].strip()
                elif line.startswith("flags") and ":" in line:
                    flags = set(line.split(":", 1)[1].split())
                    break
    except OSError:
        pass
    native = bf16_supported()
    kept = sorted(f for f in flags if f in ("avx2", "avx512f", "avx512_bf16", "amx_bf16",
                                            "amx_tile", "fma"))
    return dict(numbers="fp32" if precision == "fp32"
                else ("bf16-native" if native else "bf16-emulated"),
                precision=precision, cpu=cpu, cpu_flags=kept, torch=torch.__version__)


def _numbers_text(numbers: str) -> str:
    return {"fp32": "in fp32", "bf16-native": "in bf16 on a CPU with native bf16 (AVX512-BF16 "
            "or AMX)", "bf16-emulated": "in bf16 emulated on a CPU without native bf16"
            }.get(numbers, numbers)


class RunStore:
    """What a reproduction has finished, under ``root``: one JSON file per frame (its rows,
    the revision that computed them and this machine's :func:`arithmetic`), ``calibration.json``
    (the h betas), ``conformal.json`` (g's robust conformal calibrations) and ``identity.json``
    (per identity: its parts, the full design table and the arithmetic it was begun with), each
    written atomically and reused only by a run with the same identity (:meth:`identity`). A
    stopped run resumes where it stopped."""

    def __init__(self, root):
        from pathlib import Path

        from drake_cert.io import git_revision

        self.root = Path(root)
        self.revision = git_revision()
        self.computed_by: dict[tuple[str, int], str] = {}  # frame -> revision that computed it
        self._entries: dict[str, dict] = {}  # identity -> its manifest entry (this run's)
        self._recorded: set[str] = set()  # identities whose entry is in the manifest
        self._arithmetic: dict | None = None

    # ------------------------------------------------------------------ identity
    def manifest(self) -> dict:
        """``identity.json``: identity -> its parts, design table and arithmetic ({} if none)."""
        import json

        path = self.root / MANIFEST
        try:
            return json.loads(path.read_text()) if path.exists() else {}
        except (OSError, ValueError):
            return {}

    def identity(self, config: ReproduceConfig, designs: list) -> str:
        """The run's identity, its design table read as one this store holds when it is the
        same design table (:func:`canonical_designs`)."""
        references = [entry["designs"] for entry in self.manifest().values()
                      if "designs" in entry]
        parts = identity_parts(config, designs, references)
        identity = identity_of(parts)
        self._entries[identity] = dict(parts, arithmetic=self.arithmetic(config.precision),
                                       begun_by_revision=self.revision)
        return identity

    def arithmetic(self, precision: str) -> dict:
        if self._arithmetic is None or self._arithmetic["precision"] != precision:
            self._arithmetic = arithmetic(precision)
        return self._arithmetic

    def precisions(self) -> list[str]:
        """The precisions of the identities this store holds, oldest first."""
        return list(dict.fromkeys(e["settings"]["precision"] for e in self.manifest().values()
                                  if "settings" in e))

    def check_arithmetic(self, identity: str, precision: str) -> None:
        """:class:`ConfigError` when frames of ``identity`` were begun in another kind of bf16
        than this CPU's: finishing the run here would mix digits of two arithmetics."""
        entry = self.manifest().get(identity)
        if entry is None or "arithmetic" not in entry:
            return
        stored, here = entry["arithmetic"]["numbers"], self.arithmetic(precision)["numbers"]
        if stored != here:
            raise ConfigError(
                f"{self.root} was made {_numbers_text(stored)}; this CPU "
                f"({self.arithmetic(precision)['cpu']}) computes {_numbers_text(here)}, which "
                "gives the same discrete outcomes but other digits: finish the run on a CPU "
                "like the first, rewrite its tables with --from-store (nothing is computed), "
                "or start afresh with --fresh")

    def explain(self, config: ReproduceConfig, designs: list) -> str:
        """Why no stored frame matches ``config`` and ``designs``: what differs from the
        identity the store was last written with ("" when the store has no manifest)."""
        from drake_cert.certification.sampler import bf16_supported

        entries = self.manifest()
        if not entries:
            return ""
        import json

        stored = list(entries.values())[-1]
        current = json.loads(json.dumps(identity_parts(config, designs), default=str))  # as read
        notes = []
        settings = [k for k in sorted(set(current["settings"]) | set(stored["settings"]))
                    if current["settings"].get(k) != stored["settings"].get(k)]
        for key in settings:
            notes.append(f"{key} {stored['settings'].get(key)!r} there, "
                         f"{current['settings'].get(key)!r} here")
        if "precision" in settings:
            made = stored.get("arithmetic", {}).get("numbers", stored["settings"]["precision"])
            notes[settings.index("precision")] = (
                f"made {_numbers_text(made)}; this CPU "
                f"{'has' if bf16_supported() else 'has no'} native bf16 and runs "
                f"{current['settings']['precision']} (pass --precision "
                f"{stored['settings']['precision']})")
        for part, what in (("models", "model"), ("data", "data file")):
            here, there = current[part], stored[part]
            notes += [f"{what} {k} differs" for k in sorted(set(here) | set(there))
                      if here.get(k) != there.get(k)]
        why = same_design_table(stored["designs"], design_dicts(designs))
        if why:
            notes.append(f"the design table differs beyond {DESIGN_RTOL:g} relative from the "
                         f"one its frames were made with ({why}; theirs first)")
        return "; ".join(notes)

    def _record(self, identity: str) -> None:
        """Add ``identity``'s manifest entry (parts, design table, arithmetic) when new."""
        import json

        from drake_cert.io import atomic_write_text

        entry = self._entries.get(identity)
        if entry is None or identity in self._recorded:
            return
        self._recorded.add(identity)
        manifest = self.manifest()
        if identity not in manifest:
            manifest[identity] = entry
            atomic_write_text(self.root / MANIFEST, json.dumps(manifest, indent=1,
                                                               default=str) + "\n")

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
        if stored is None:
            return None
        self.computed_by[(task.preset, task.position)] = stored.get(
            "computed_by_revision", stored.get("git_revision", "unknown"))
        return stored["rows"]

    def put_frame(self, identity: str, task: FrameTask, rows: list[dict],
                  cpu_s: float | None = None) -> None:
        """Store a frame's rows; ``cpu_s`` (its workers' CPU seconds) goes to the ledger."""
        entry = self._entries.get(identity)
        extra = {} if entry is None else dict(
            arithmetic=self.arithmetic(entry["settings"]["precision"]))
        self._write(self._frame_path(task), identity, rows=rows, **extra)
        self.computed_by[(task.preset, task.position)] = self.revision
        self._charge(identity, "frames", cpu_s)

    def revisions(self, tasks) -> list[str]:
        """The revisions that computed the frames of ``tasks`` (read or written here)."""
        return sorted({self.computed_by[(t.preset, t.position)] for t in tasks
                       if (t.preset, t.position) in self.computed_by})

    def add_cpu(self, identity: str, stage: str, seconds: float) -> None:
        """Add ``seconds`` of the workers' CPU time to ``stage`` of ``identity``'s ledger
        (``cpu.json``), as each part is stored: the run's cost, whichever invocations made it
        (a stopped invocation's finished parts included; its unfinished ones are not)."""
        import json

        from drake_cert.io import atomic_write_text

        path = self.root / CPU_LEDGER
        ledger = self._ledger()
        entry = ledger.setdefault(identity, {})
        entry[stage] = entry.get(stage, 0.0) + float(seconds)  # rounded when read
        entry[f"{stage}_parts"] = entry.get(f"{stage}_parts", 0) + 1
        atomic_write_text(path, json.dumps(ledger, indent=1, sort_keys=True) + "\n")

    def cpu(self, identity: str) -> dict:
        """``identity``'s ledger: CPU seconds per stage, how many parts each counts, and their
        sum (``all``); {} when the store has none (made before the ledger)."""
        entry = self._ledger().get(identity, {})
        if not entry:
            return {}
        seconds = {k: v for k, v in entry.items() if not k.endswith("_parts")}
        return dict({k: round(v, 1) for k, v in entry.items()},
                    all=round(sum(seconds.values()), 1))

    def _ledger(self) -> dict:
        import json

        try:
            return json.loads((self.root / CPU_LEDGER).read_text())
        except (OSError, ValueError):
            return {}

    def betas(self, identity: str) -> dict:
        stored = self._read(self.root / "calibration.json", identity)
        if stored is None:
            return {}
        return {(p, float(s)): float(b) for p, s, b in stored["betas"]}

    def put_betas(self, identity: str, betas: dict, cpu_s: float | None = None) -> None:
        """Store every beta so far; ``cpu_s`` is the newest one's cost (ledger)."""
        self._write(self.root / "calibration.json", identity,
                    betas=[[p, s, b] for (p, s), b in sorted(betas.items())])
        self._charge(identity, "calibration_h", cpu_s)

    def conformal(self, identity: str) -> dict:
        from drake_cert.certification.conformal import RobustConformalCalibration

        stored = self._read(self.root / "conformal.json", identity)
        if stored is None:
            return {}
        return {(p, float(s)): RobustConformalCalibration.from_json(c)
                for p, s, c in stored["calibrations"]}

    def put_conformal(self, identity: str, calibrations: dict,
                      cpu_s: float | None = None) -> None:
        """Store every conformal calibration so far; ``cpu_s`` is the newest one's cost."""
        self._write(self.root / "conformal.json", identity,
                    calibrations=[[p, s, c.to_json()] for (p, s), c in
                                  sorted(calibrations.items())])
        self._charge(identity, "calibration_conformal", cpu_s)

    def _charge(self, identity: str, stage: str, cpu_s: float | None) -> None:
        if cpu_s is not None:
            self.add_cpu(identity, stage, cpu_s)

    def _write(self, path, identity: str, **content) -> None:
        import json

        from drake_cert.io import atomic_write_text

        self._record(identity)
        text = json.dumps(dict(identity=identity, computed_by_revision=self.revision,
                               **content), separators=(",", ":"))
        atomic_write_text(path, text + "\n")
