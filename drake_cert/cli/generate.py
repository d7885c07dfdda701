"""``drake-cert generate``: render a preset's synthetic frames; write a sample grid and/or PNGs.

``--out FILE.png`` writes a grid (one row per label, the frame's true stiffness above it);
``--export DIR`` writes a class-per-folder directory of PNG frames (the layout that
``load_image_folder`` and users' own data use) with ``stiffness.csv`` beside them.
"""

from __future__ import annotations

import io as _io
import sys
from pathlib import Path

from drake_cert.errors import ConfigError


def configure(parser) -> None:
    parser.add_argument("--preset", required=True, help="preset name, e.g. carla-like")
    parser.add_argument("--out", default=None, help="sample grid PNG to write")
    parser.add_argument("--per-class", type=int, default=8, help="grid columns (frames per label)")
    parser.add_argument("--export", default=None,
                        help="folder to write <label>/<index>.png frames and stiffness.csv into")
    parser.add_argument("--frames-per-class", type=int, default=None,
                        help="frames per label to export (default: the split's count)")
    parser.add_argument("--split", default="train", choices=("train", "calibration", "test"),
                        help="which split's frames to render (each split has its own seeds)")
    parser.add_argument("--seed", type=int, default=0, help="data seed (>= 0)")
    parser.add_argument("--size", type=int, default=64, help="frame side in pixels")
    parser.add_argument("--scale", type=int, default=2, help="grid: pixels per frame pixel")
    parser.add_argument("--conditions", default=None, help="conditions YAML (default: shipped)")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads")


def check(args) -> None:
    """Options, ``--conditions`` and output paths, before torch is imported (``cli.main`` runs
    this first); keeps the conditions table as ``args.table``."""
    from drake_cert.config import check_frame_size, load_conditions

    if args.out is None and args.export is None:
        raise ConfigError("nothing to do: give --out FILE.png and/or --export DIR")
    for key in ("per_class", "size", "scale"):
        if getattr(args, key) <= 0:
            raise ConfigError(f"--{key.replace('_', '-')} {getattr(args, key)} must be positive")
    check_frame_size(args.size, "--size")
    if args.seed < 0:
        raise ConfigError(f"--seed {args.seed} must be >= 0")
    args.table = load_conditions(args.conditions)
    args.table.preset(args.preset)
    check_outputs(args)


def run(args) -> int:
    import torch

    from drake_cert.perception.datasets import load_split

    torch.set_num_threads(max(1, int(args.threads)))
    if not hasattr(args, "table"):
        check(args)
    table = args.table
    count = args.frames_per_class
    if args.export is None:
        count = args.per_class
    frames = load_split(args.preset, args.split, seed=args.seed, size=args.size,
                        frames_per_class=count, conditions=table)
    if args.out is not None:
        path = write_sample_grid(frames.per_class(args.per_class), args.out, scale=args.scale)
        print(f"drake-cert generate: wrote {path}", file=sys.stderr)
    if args.export is not None:
        n = export_frames(frames, args.export)
        print(f"drake-cert generate: wrote {n} frames to {args.export}", file=sys.stderr)
    return 0


def check_outputs(args) -> None:
    """Fail in one line before rendering when --out or --export cannot be written."""
    from drake_cert.io import check_writable

    if args.out is not None:
        check_writable(args.out, "--out")
    if args.export is not None:
        check_writable(Path(args.export) / "stiffness.csv", "--export")


def write_sample_grid(frames, out: str | Path, *, scale: int = 2) -> Path:
    """A PNG grid: one row per label (name on the left), stiffness in kN/rad above each frame."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from drake_cert.io import atomic_write_bytes

    k = len(frames.label_names)
    cols = max(int((frames.labels == i).sum()) for i in range(k))
    inch = frames.size * scale / 100
    fig, axes = plt.subplots(k, cols, figsize=(cols * inch + 1.0, k * (inch + 0.25)),
                             squeeze=False, dpi=100)
    for i, label in enumerate(frames.label_names):
        idx = (frames.labels == i).nonzero().flatten().tolist()
        for j in range(cols):
            ax = axes[i, j]
            ax.set_xticks([])
            ax.set_yticks([])
            for spine in ax.spines.values():
                spine.set_visible(False)
            if j < len(idx):
                ax.imshow(frames.images[idx[j]].permute(1, 2, 0).numpy(), interpolation="nearest")
                c = float(frames.stiffness_n_per_rad[idx[j]])
                ax.set_title(f"{c / 1e3:.0f} kN/rad", fontsize=7)
            if j == 0:
                ax.set_ylabel(label, fontsize=9)
    fig.suptitle(f"{frames.preset}: synthetic frames (rows: road condition, grippiest first)",
                 fontsize=9)
    fig.tight_layout()
    buf = _io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    return atomic_write_bytes(out, _palette_png(buf.getvalue()))


def _palette_png(png: bytes) -> bytes:
    """Re-encode a PNG with a 256-colour palette (a docs-sized file; the frames stay legible)."""
    from PIL import Image

    with Image.open(_io.BytesIO(png)) as im:
        small = im.convert("RGB").quantize(colors=256, method=Image.Quantize.MEDIANCUT)
        out = _io.BytesIO()
        small.save(out, format="PNG", optimize=True)
    return out.getvalue()


def export_frames(frames, folder: str | Path) -> int:
    """Write ``folder/<label>/<index>.png`` (8-bit RGB) and ``folder/stiffness.csv``."""
    import numpy as np
    from PIL import Image

    from drake_cert.io import atomic_write_text

    root = Path(folder)
    rows = ["file,label,stiffness_n_per_rad"]
    for i in range(len(frames)):
        label = frames.label_names[int(frames.labels[i])]
        arr = (frames.images[i].permute(1, 2, 0).numpy() * 255.0).round().astype(np.uint8)
        rel = Path(label) / f"{i:06d}.png"
        (root / label).mkdir(parents=True, exist_ok=True)
        Image.fromarray(arr).save(root / rel)
        rows.append(f"{rel.as_posix()},{label},{float(frames.stiffness_n_per_rad[i]):.1f}")
    atomic_write_text(root / "stiffness.csv", "\n".join(rows) + "\n")
    return len(frames)
