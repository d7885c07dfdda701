"""The reproduction's headline: how often the car left its lane, not conditioned on the truth.

Input: a reproduction's frame rows (:mod:`drake_cert.experiments.reproduce`, or ``frames.csv``
read back by :func:`read_frames_csv`), one per test frame and cell, saying whether the episode
on the Fiala plant left the lane. For every pipeline in the rows (whatever its name: ``f``,
``g``, ``g_conformal``, ``f_reg``, ``h``, ...), per selection (every attacked episode; each
attack at each budget) and scope (all presets; each preset):

* the *episode share*: among the pipeline's attacked episodes (only those certified at the
  attack's budget, for a pipeline any of whose rows has ``certified`` true; all of them for one
  that does not, such as f and f_reg), the share that left the lane;
* the *frame share*: among the frames with at least one such episode, the share with at
  least one departure.

Neither asks whether the certified label range holds the true label. Intervals (95%): the
episode share by a per-frame cluster bootstrap (frames keyed by preset and frame, drawn with
replacement, ``resamples`` = 10,000 times with ``numpy.random.default_rng(seed)``, seed 0, a
fresh generator per selection; where every resample gives the same share, the frame share's
interval instead); the frame share by an exact two-sided Clopper-Pearson interval over frames.
Both assume the test frames are a random sample of the frames the car will see. Why these
figures and intervals: DESIGN 7.3. :func:`truth_conditioned` gives the split by whether the
certified range holds the true label, a diagnostic of the controller designs only.
"""

from __future__ import annotations

import csv
import math
from collections import defaultdict
from pathlib import Path

import numpy as np

from drake_cert.errors import ConfigError

RESAMPLES = 10_000  # per-frame cluster bootstrap draws
SEED = 0  # the bootstrap's seed
LEVEL = 0.95  # two-sided confidence level of every interval

ALL = "all"  # the selection of every attacked episode (each attack, budget and sigma)

_BOOL = ("interval_covers", "certified", "left_lane")
_FLOAT = ("stiffness_n_per_rad", "friction_mu", "sigma", "eps", "interval_lo", "interval_hi",
          "certificate", "safe_set_radius", "velocity_mps", "peak_abs_e1_m")
_INT = ("frame", "position")
_NEEDED = ("preset", "frame", "pipeline", "attack", "eps", "certified", "left_lane",
           "true_label", "design_labels")

DIAGNOSTIC_NOTE = (
    "Where the certified label range (the labels of the design in force) holds the true label, "
    "the design was synthesized for the true condition's stiffness and a friction no higher "
    "than the true one, so no pipeline, the non-robust f included, should leave its lane there: "
    "this split tests the controller designs, not the certificate, and it conditions on a truth "
    "the car never sees. The certificate's work shows in how rarely the range misses the truth "
    "under attack, which the unconditioned shares above count.")


def read_frames_csv(path: str | Path, rename: dict[str, str] | None = None) -> list[dict]:
    """Frame rows from a reproduction's ``frames.csv``, typed as the run wrote them (booleans,
    floats in SI units, ints; a regression row's ``predicted`` a float in N/rad). ``rename``
    maps pipeline names (e.g. ``{"g": "g_conformal"}`` for a companion run with the robust
    conformal interval). Raises :class:`ConfigError` for a missing file or column."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ConfigError(f"cannot read frame rows {path}: {exc.strerror or exc}") from None
    reader = csv.DictReader(text.splitlines())
    missing = [c for c in _NEEDED if c not in (reader.fieldnames or [])]
    if missing:
        raise ConfigError(f"{path} is not a reproduction's frames.csv: no column "
                          f"{', '.join(missing)}")
    rows = []
    for raw in reader:
        r = dict(raw)
        try:
            for k in _BOOL:
                if k in r:
                    r[k] = r[k] == "True"
            for k in _FLOAT:
                if k in r:
                    r[k] = float(r[k]) if r[k] != "" else math.nan
            for k in _INT:
                if k in r:
                    r[k] = int(r[k])
            if r.get("task") == "regress":  # "": no point estimate (h decided sequentially)
                r["predicted"] = float(r["predicted"]) if r["predicted"] != "" else None
        except ValueError as exc:
            raise ConfigError(f"{path} line {reader.line_num}: {exc}") from None
        if rename:
            r["pipeline"] = rename.get(r["pipeline"], r["pipeline"])
        rows.append(r)
    return rows


def holds_true_label(row: dict) -> bool:
    """Whether the label range of the design in force holds the frame's true label."""
    return row["true_label"] in str(row["design_labels"]).split("+")


def certifying_pipelines(rows: list[dict]) -> set[str]:
    """Pipelines with a certificate: those with at least one certified row."""
    return {r["pipeline"] for r in rows if r["certified"]}


def _clopper_pearson(hits: int, total: int, level: float) -> tuple[float, float]:
    """Two-sided exact interval of a binomial share (fractions); ``(0, 1)`` with no trial."""
    from drake_cert.certification.statistics import clopper_pearson_one_sided

    if total == 0:
        return 0.0, 1.0
    lo, hi = clopper_pearson_one_sided(hits, total, (1 - level) / 2)
    return float(lo), float(hi)


def _cluster(row: dict) -> tuple:
    return (row["preset"], row["frame"])


def cluster_bootstrap_share(hits: np.ndarray, totals: np.ndarray, *,
                            resamples: int = RESAMPLES, seed: int = SEED,
                            level: float = LEVEL) -> tuple[float, float]:
    """Percentile interval of ``sum(hits) / sum(totals)`` by resampling clusters: ``hits[i]``
    departures among ``totals[i]`` episodes of cluster i; the clusters are drawn with
    replacement, as many as there are, ``resamples`` times (``default_rng(seed)``). Resamples
    with no episode are dropped. Returns ``(low, high)`` as fractions."""
    hits, totals = np.asarray(hits, dtype=np.int64), np.asarray(totals, dtype=np.int64)
    m = len(totals)
    if m == 0 or totals.sum() == 0:
        return 0.0, 1.0
    rng = np.random.default_rng(seed)
    shares = []
    for start in range(0, resamples, 1000):  # chunks: 1000 x m indices at a time
        idx = rng.integers(0, m, size=(min(1000, resamples - start), m))
        t = totals[idx].sum(axis=1)
        h = hits[idx].sum(axis=1)
        shares.append(h[t > 0] / t[t > 0])
    shares = np.concatenate(shares)
    tail = (1 - level) / 2
    lo, hi = np.quantile(shares, [tail, 1 - tail])
    return float(lo), float(hi)


def departure_shares(rows: list[dict], *, certified_only: bool, resamples: int = RESAMPLES,
                     seed: int = SEED, level: float = LEVEL) -> dict:
    """Episode and frame shares of departures over ``rows`` (one pipeline's attacked episodes
    of one selection): with ``certified_only``, the episodes are the certified rows. Every
    frame in ``rows`` is a cluster of the bootstrap (a frame with no certified episode weighs
    0 episodes in a resample). Shares in % (None with no episode), intervals as
    ``[low, high]`` in % (``[0, 100]`` with no episode)."""
    per_frame: dict[tuple, list[int]] = defaultdict(lambda: [0, 0])
    for r in rows:
        counts = per_frame[_cluster(r)]
        if r["certified"] or not certified_only:
            counts[1] += 1
            counts[0] += bool(r["left_lane"])
    hits = np.array([c[0] for c in per_frame.values()], dtype=np.int64)
    totals = np.array([c[1] for c in per_frame.values()], dtype=np.int64)
    k, n = int(hits.sum()), int(totals.sum())
    frames = int((totals > 0).sum())
    frames_hit = int((hits > 0).sum())
    f_lo, f_hi = _clopper_pearson(frames_hit, frames, level)
    if 0 < k < n:
        lo, hi = cluster_bootstrap_share(hits, totals, resamples=resamples, seed=seed,
                                         level=level)
        method = "cluster_bootstrap"
    else:  # no spread to resample: the frame share's exact interval
        lo, hi = f_lo, f_hi
        method = "clopper_pearson_frames"
    return dict(attacked=len(rows), episodes=n, departures=k,
                pct=100.0 * k / n if n else None, ci95_pct=[100.0 * lo, 100.0 * hi],
                ci95_method=method,
                frames=frames, frames_departed=frames_hit,
                frames_pct=100.0 * frames_hit / frames if frames else None,
                frames_ci95_pct=[100.0 * f_lo, 100.0 * f_hi])


def _selections(rows: list[dict]) -> list[tuple[str, str | None, float | None]]:
    """(name, attack, eps): every attacked episode, then each attack at each budget."""
    out = [(ALL, None, None)]
    for attack in ("sa", "ea"):
        out += [(f"{attack.upper()} eps = {e:g}", attack, e)
                for e in sorted({r["eps"] for r in rows if r["attack"] == attack})]
    return out


def headline(rows: list[dict], *, resamples: int = RESAMPLES, seed: int = SEED,
             level: float = LEVEL) -> dict:
    """Departure shares per pipeline, selection (every attacked episode; each attack at each
    budget) and scope (all presets; each preset), see the module docstring. Returns
    ``dict(method=..., resamples, seed, level, rows=[...])``; each row names ``pipeline``,
    ``certified_only`` (whether the episodes are the certified ones), ``selection``,
    ``attack``, ``eps``, ``preset`` (``"all"`` or a preset) and the counts and shares of
    :func:`departure_shares`."""
    certifying = certifying_pipelines(rows)
    pipelines = list(dict.fromkeys(r["pipeline"] for r in rows))
    presets = list(dict.fromkeys(r["preset"] for r in rows))
    out = []
    for pipeline in pipelines:
        attacked = [r for r in rows if r["pipeline"] == pipeline and r["attack"] != "none"]
        if not attacked:
            continue
        for name, attack, eps in _selections(attacked):
            chosen = [r for r in attacked
                      if attack is None or (r["attack"] == attack and r["eps"] == eps)]
            for preset in [ALL, *presets]:
                mine = [r for r in chosen if preset == ALL or r["preset"] == preset]
                if not mine:
                    continue
                out.append(dict(pipeline=pipeline, certified_only=pipeline in certifying,
                                selection=name, attack=attack or ALL, eps=eps, preset=preset,
                                **departure_shares(mine, certified_only=pipeline in certifying,
                                                   resamples=resamples, seed=seed,
                                                   level=level)))
    method = (f"episode share: per-frame cluster bootstrap, {resamples} resamples, seed {seed}, "
              f"percentile interval; frame share: Clopper-Pearson over frames; level {level}")
    return dict(method=method, resamples=resamples, seed=seed, level=level, rows=out)


def truth_conditioned(rows: list[dict]) -> dict:
    """The diagnostic split, per pipeline: its headline episodes (certified attacked ones for
    a certifying pipeline, every attacked one otherwise) by whether the label range of the
    design in force holds the true label (``holds``) or misses it (``misses``), each as
    departures / episodes; ``every_row`` pools every row of every pipeline, clean ones
    included. See :data:`DIAGNOSTIC_NOTE` for what it tests."""
    certifying = certifying_pipelines(rows)
    out = {}
    for pipeline in dict.fromkeys(r["pipeline"] for r in rows):
        mine = [r for r in rows if r["pipeline"] == pipeline and r["attack"] != "none"
                and (r["certified"] or pipeline not in certifying)]
        if mine:
            out[pipeline] = _split(mine)
    out["every_row"] = _split(rows)
    return out


def _split(rows: list[dict]) -> dict:
    holds = [r for r in rows if holds_true_label(r)]
    misses = [r for r in rows if not holds_true_label(r)]
    return dict(holds=dict(departures=sum(bool(r["left_lane"]) for r in holds),
                           episodes=len(holds)),
                misses=dict(departures=sum(bool(r["left_lane"]) for r in misses),
                            episodes=len(misses)))


def display_names(interval: str = "safe_set") -> dict[str, str]:
    """Display names of the pipelines; ``interval``: the run's interval for ``g``
    (``"safe_set"`` or ``"conformal"``, :class:`ReproduceConfig`'s ``interval``)."""
    return {"f": "f (non-robust)",
            "g": "g (robust conformal interval)" if interval == "conformal"
            else "g (safe-set interval: the paper's, assumes g right on the clean frame)",
            "g_conformal": "g (robust conformal interval, the drive's calibration)",
            "f_reg": "f_reg (non-robust regressor)", "h": "h (median-smoothed regressor)"}


def _name(pipeline: str, names: dict | None) -> str:
    return (names or {}).get(pipeline, pipeline)


def _share_text(s: dict) -> str:
    """An episode share; its interval marked * where it is Clopper-Pearson over frames (no
    departure, or all: the bootstrap has no spread)."""
    if not s["episodes"]:
        return "n/a"
    lo, hi = s["ci95_pct"]
    mark = "*" if s.get("ci95_method") == "clopper_pearson_frames" else ""
    return (f"{s['departures']:,} / {s['episodes']:,} = {s['pct']:.2f}% "
            f"[{lo:.2f}, {hi:.2f}]{mark}")


# The order pipelines are shown in: the assumption-free interval (the drive's) before the paper's.
SHOWN_ORDER = ("f", "g_conformal", "g", "f_reg", "h")


def _shown(pipelines) -> list[str]:
    return sorted(pipelines, key=lambda p: SHOWN_ORDER.index(p) if p in SHOWN_ORDER
                  else len(SHOWN_ORDER))


def _frames_text(s: dict) -> str:
    if not s["frames"]:
        return "n/a"
    lo, hi = s["frames_ci95_pct"]
    return f"{s['frames_departed']} / {s['frames']} = {s['frames_pct']:.1f}% [{lo:.1f}, {hi:.1f}]"


def markdown(result: dict, diagnostic: dict | None = None, *, main_eps: float | None = None,
             names: dict[str, str] | None = None) -> str:
    """The headline as Markdown: every pipeline over all its attacked episodes and at the main
    budget, then each budget side by side, each preset, and the truth-conditioned diagnostic.
    ``names`` gives a pipeline's display name (e.g. ``{"g": "g (safe-set interval)"}``)."""
    rows = result["rows"]
    pipelines = _shown(dict.fromkeys(r["pipeline"] for r in rows))

    def get(pipeline, selection, preset=ALL):
        return next((r for r in rows if r["pipeline"] == pipeline and r["selection"] == selection
                     and r["preset"] == preset), None)

    def which(pipeline):
        r = next(r for r in rows if r["pipeline"] == pipeline)
        return "certified attacked" if r["certified_only"] else "attacked (no certificate)"

    level = f"{100 * result['level']:g}%"
    lines = [f"**Left the lane, not conditioned on the truth** ({level} intervals: episodes by "
             f"a per-frame cluster bootstrap, {result['resamples']:,} resamples, seed "
             f"{result['seed']}, since departures cluster by frame; frames by Clopper-Pearson "
             "over frames. A certifying pipeline counts the attacked episodes whose run-time "
             "interval was certified at the attack's budget; f and f_reg, which certify "
             "nothing, count every attacked episode. * marks an episode interval that is "
             "Clopper-Pearson over frames: with no departure, or all, the bootstrap has no "
             "spread.)", "",
             "| pipeline | episodes | selection | left the lane (episodes) | frames with a "
             "departure |", "|---|---|---|---|---|"]
    main = [ALL] + ([f"SA eps = {main_eps:g}"] if main_eps is not None else [])
    for pipeline in pipelines:
        for selection in main:
            s = get(pipeline, selection)
            if s is None:
                continue
            title = "every attack, budget and sigma" if selection == ALL else selection
            lines.append(f"| {_name(pipeline, names)} | {which(pipeline)} "
                         f"({s['episodes']:,} of {s['attacked']:,}) | {title} | "
                         f"{_share_text(s)} | {_frames_text(s)} |")
    selections = list(dict.fromkeys(r["selection"] for r in rows if r["selection"] != ALL))
    lines += ["", "**By attack and budget** (pipelines side by side; episodes left the lane, "
              f"{level} cluster bootstrap)", "",
              "| selection | " + " | ".join(_name(p, names) for p in pipelines) + " |",
              "|---|" + "---|" * len(pipelines)]
    for selection in selections:
        lines.append(f"| {selection} | " + " | ".join(
            _share_text(s) if (s := get(p, selection)) else "" for p in pipelines) + " |")
    presets = list(dict.fromkeys(r["preset"] for r in rows if r["preset"] != ALL))
    lines += ["", "**By preset** (every attack, budget and sigma; episodes left the lane, "
              f"{level} cluster bootstrap; frames with a departure)", "",
              "| pipeline | " + " | ".join(presets) + " |", "|---|" + "---|" * len(presets)]
    for pipeline in pipelines:
        lines.append(f"| {_name(pipeline, names)} | " + " | ".join(
            f"{_share_text(s)}; frames {s['frames_departed']}/{s['frames']}"
            if (s := get(pipeline, ALL, p)) else "" for p in presets) + " |")
    if diagnostic:
        lines += ["", "**Diagnostic: split by whether the certified label range holds the "
                  "true label** (same episodes as above; departures / episodes)", "",
                  "| pipeline | range holds the true label | range misses it |", "|---|---|---|"]
        for pipeline, d in sorted(diagnostic.items(), key=lambda kv: (
                kv[0] == "every_row", _shown(diagnostic).index(kv[0]))):
            title = ("every row of every pipeline (clean included)" if pipeline == "every_row"
                     else _name(pipeline, names))
            lines.append(f"| {title} | {d['holds']['departures']:,} / "
                         f"{d['holds']['episodes']:,} | {d['misses']['departures']:,} / "
                         f"{d['misses']['episodes']:,} |")
        lines += ["", DIAGNOSTIC_NOTE]
    return "\n".join(lines) + "\n"
