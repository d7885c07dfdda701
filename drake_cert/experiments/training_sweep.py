"""The training sweep: which classifier certifies the most without certifying wrong more.

For one preset and sigma, each candidate model (the baseline, by default the shipped model, and
those ``drake-cert sweep`` trains: consistency at each lambda and the tail loss at each (q, beta),
at each width) is certified on the same held-out
test frames, clean and under the stability attack (SmoothAdv on g) at each budget eps, by
:func:`~drake_cert.experiments.perception_eval.certify_classifier`, the function ``drake-cert
certify`` runs. Each cell reports the three outcomes of the run-time label range at eps
(:func:`~drake_cert.experiments.perception_eval.decision_shares`: certified right, certified
wrong, abstain) with 95 % Clopper-Pearson intervals.

The pick (:func:`pick_candidate`, docs/design.md 3.2): among the candidates whose
certified-wrong share is, in every cell, not above the baseline's 95 % upper bound in that
cell, the one that abstains least in the ranking cell (by default the stability attack at
eps = sigma, the drive's budget), or with ``rank="tail"`` the one with the thinnest worst-label
own-label tail (:func:`own_label_tail`, the frames that set the drive's conformal thresholds);
the baseline itself always qualifies, so the pick never certifies wrong more than today's model
by more than the baseline's own sampling error.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import math
from collections.abc import Callable, Iterable
from pathlib import Path

from drake_cert.certification.seeds import frame_choice_seed
from drake_cert.config import ConditionsTable
from drake_cert.errors import ConfigError
from drake_cert.experiments.perception_eval import (
    CalibrationInputs,
    CertifySettings,
    EvalFrames,
    certify_classifier,
    clopper_pearson_interval,
    json_safe,
    select_frames,
)
from drake_cert.io import atomic_write_text

OUTCOMES = ("certified_right", "certified_wrong", "interval_abstain")
RANKS = ("abstain", "tail")
TAIL_SHARE = 0.5  # a frame is in its label's tail when g gives its own label under half the votes
DATA_SEED = 0  # the synthetic splits the shipped models were trained and tested on


@dataclasses.dataclass(frozen=True)
class Candidate:
    """One model of the sweep: a name, and the ``drake-cert train`` options that make it
    (None: an existing file, e.g. the shipped model)."""

    name: str
    train_options: tuple[str, ...] | None = None


def default_candidates(lambdas: Iterable[float], tails: Iterable[tuple[float, float]] = (),
                       widths: Iterable[int] = (16,), pools: Iterable[int] = (1,),
                       copies: int = 2, eta: float = 0.5) -> list[Candidate]:
    """The baseline (an existing file: by default the shipped model), then at each network
    width and input pooling: consistency regularization at each lambda (m = ``copies``,
    ``eta``) and the tail-weighted loss at each ``(q, beta)`` (docs/design.md 3.2). Names carry
    the width when it is not the default 16 (tail candidates always carry it) and the pooling
    when it is not 1 (``_p2``)."""
    out = [Candidate("baseline")]
    for width, pool in itertools.product(widths, pools):
        if int(width) < 1:
            raise ConfigError(f"width {width} must be a whole number >= 1")
        if int(pool) < 1:
            raise ConfigError(f"pool {pool} must be a whole number >= 1")
        size = ("--width", str(int(width))) + (("--pool", str(int(pool))) if pool != 1 else ())
        pooled = "" if int(pool) == 1 else f"_p{int(pool)}"
        suffix = ("" if int(width) == 16 else f"_w{int(width)}") + pooled
        for lam in lambdas:
            if not (math.isfinite(lam) and lam >= 0):
                raise ConfigError(f"lambda {lam} must be a finite number >= 0")
            out.append(Candidate(f"consistency_l{lam:g}{suffix}",
                                 ("--method", "consistency", "--consistency-lambda",
                                  f"{lam:g}", "--consistency-eta", f"{eta:g}", "--copies",
                                  str(copies), *size)))
        for q, beta in tails:
            if not (0 < q <= 1 and 0 <= beta <= 1):
                raise ConfigError(f"tail (q {q:g}, beta {beta:g}): q must be in (0, 1] and "
                                  "beta in [0, 1]")
            out.append(Candidate(f"tail_q{q:g}_b{beta:g}_w{int(width)}{pooled}",
                                 ("--method", "tail", "--tail-fraction", f"{q:g}",
                                  "--tail-weight", f"{beta:g}", *size)))
    return out


@dataclasses.dataclass(frozen=True)
class SweepSettings:
    """How every candidate is certified (budgets: L2 in [0, 1] pixel space)."""

    preset: str
    sigma: float
    budgets: tuple[float, ...] = (1.0,)
    attacks: tuple[str, ...] = ("none", "sa")
    frames: int = 600  # held-out test frames, round-robin over labels, the same for all
    n0: int = 100
    n: int = 1000
    alpha: float = 1.0e-4  # about the per-tick share of a drive's alpha (0.01 over ~100 ticks)
    attack_steps: int = 10
    attack_noise_draws: int = 4
    batch_size: int = 1000
    device: str = "cpu"
    precision: str = "fp32"
    seed: int = 0
    rank_attack: str = "sa"
    rank_eps: float | None = None  # None: sigma
    rank: str = "abstain"  # or "tail": the eligible candidate with the thinnest own-label tail

    def __post_init__(self):
        if self.sigma <= 0:
            raise ConfigError("the sweep compares smoothed classifiers: sigma must be > 0")
        if not self.budgets or any(not (math.isfinite(e) and e >= 0) for e in self.budgets):
            raise ConfigError(f"budgets {self.budgets} must be finite numbers >= 0")
        if self.rank_attack not in self.attacks or self.ranking_eps not in self.budgets:
            raise ConfigError(f"the ranking cell ({self.rank_attack}, eps "
                              f"{self.ranking_eps:g}) is not among the cells evaluated")
        if self.rank not in RANKS:
            raise ConfigError(f"rank {self.rank!r}: choose one of {', '.join(RANKS)}")

    @property
    def ranking_eps(self) -> float:
        return self.sigma if self.rank_eps is None else float(self.rank_eps)

    def certify_settings(self, attack: str, eps: float) -> CertifySettings:
        return CertifySettings(
            preset=self.preset, sigma=self.sigma, attack=attack, eps=eps, n0=self.n0, n=self.n,
            alpha=self.alpha, frames=self.frames, batch_size=self.batch_size, seed=self.seed,
            device=self.device, compile="off", attack_steps=self.attack_steps,
            attack_noise_draws=self.attack_noise_draws, precision=self.precision)


def evaluate_candidate(model, test, settings: SweepSettings, table: ConditionsTable,
                       progress: Callable[[Iterable], Iterable] | None = None
                       ) -> tuple[list[dict], dict]:
    """``(rows, tail)``: one row per (attack, eps) cell with the model's three outcome shares on
    the sweep's frames (the clean certificates are computed once and shared by the cells), and
    :func:`own_label_tail` of the clean certificates."""
    index = select_frames(test.labels, settings.frames, frame_choice_seed(settings.seed))
    images, labels = test.images[index], test.labels[index]
    stiffness = test.stiffness_n_per_rad[index]
    clean_cache: dict = {}
    rows, tail = [], None
    for attack in settings.attacks:
        for eps in settings.budgets:
            cs = settings.certify_settings(attack, eps)
            records, summary = certify_classifier(
                model, EvalFrames(images, labels, stiffness, tuple(test.label_names)), table,
                cs, progress, CalibrationInputs(clean_cache=clean_cache))
            row = {"attack": attack, "eps": eps, "frames": summary["frames"],
                   "accuracy": summary["accuracy"]}
            for name in OUTCOMES:
                row[name] = summary[f"{name}_rate"]
                row[f"{name}_ci95"] = summary[f"{name}_rate_ci95"]
            rows.append(row)
            if tail is None:
                tail = own_label_tail(records, test.label_names)
    return rows, tail


def own_label_tail(records: list[dict], label_names: Iterable[str]) -> dict:
    """Per true label: how many of its frames g gives under :data:`TAIL_SHARE` of the n
    estimation votes at the clean frame (``records`` of ``certify_classifier``, whose
    ``clean_own_share`` is that share), the share with its 95 % Clopper-Pearson interval, and
    the lowest own-label share. These frames set the robust conformal thresholds (docs/design.md
    3.6): the thinner this tail, the tighter the drive's label sets."""
    out = {}
    for lab, name in enumerate(label_names):
        shares = [r["clean_own_share"] for r in records if r["label"] == lab]
        under = sum(s < TAIL_SHARE for s in shares)
        out[name] = {"frames": len(shares), "under_half": under,
                     "share": under / len(shares) if shares else 0.0,
                     "share_ci95": list(clopper_pearson_interval(under, len(shares))),
                     "lowest": min(shares) if shares else None}
    return out


def worst_tail(tail: dict) -> float:
    """The largest per-label tail share of :func:`own_label_tail`."""
    return max(v["share"] for v in tail.values())


def pick_candidate(results: dict[str, list[dict]], settings: SweepSettings,
                   tails: dict[str, dict] | None = None, baseline: str = "baseline") -> dict:
    """The candidate to ship (module docstring): ``{"pick", "eligible", "reasons"}``, where
    ``reasons[name]`` says why a candidate was not eligible. With ``settings.rank == "tail"``
    the eligible candidate with the smallest worst-label tail (``tails[name]``, of
    :func:`own_label_tail`) wins, abstentions breaking ties."""
    if baseline not in results:
        raise ConfigError(f"the sweep has no baseline {baseline!r} to compare with")
    bound = {(r["attack"], r["eps"]): r["certified_wrong_ci95"][1] for r in results[baseline]}
    eligible, reasons = [], {}
    for name, rows in results.items():
        over = [r for r in rows if r["certified_wrong"] > bound[(r["attack"], r["eps"])]]
        if over and name != baseline:
            r = over[0]
            reasons[name] = (f"certifies wrong {r['certified_wrong']:.3f} under {r['attack']} "
                             f"at eps {r['eps']:g}, above {baseline}'s upper bound "
                             f"{bound[(r['attack'], r['eps'])]:.3f}")
        else:
            eligible.append(name)

    def abstain(name: str) -> float:
        return next(r["interval_abstain"] for r in results[name]
                    if r["attack"] == settings.rank_attack and r["eps"] == settings.ranking_eps)

    if settings.rank == "tail" and (tails is None or set(tails) != set(results)):
        raise ConfigError("ranking by the tail needs every candidate's own-label tail")

    def key(name: str) -> tuple:
        first = (worst_tail(tails[name]),) if settings.rank == "tail" else ()
        return (*first, abstain(name), name != baseline)

    best = min(eligible, key=key)
    return {"pick": best, "eligible": eligible, "reasons": reasons,
            "ranking": {"attack": settings.rank_attack, "eps": settings.ranking_eps,
                        "by": settings.rank}}


def _share(row: dict, name: str) -> str:
    lo, hi = row[f"{name}_ci95"]
    return f"{row[name]:.3f} [{lo:.3f}, {hi:.3f}]"


def render(results: dict[str, list[dict]], choice: dict, settings: SweepSettings,
           header: Iterable[str] = (), tails: dict[str, dict] | None = None) -> str:
    """Markdown of the sweep: one row per candidate and cell, each candidate's own-label tail
    per label (when given), and the pick with its reason."""
    lines = [f"# Training sweep: {settings.preset}, sigma = {settings.sigma:g}", "", *header,
             f"Every candidate certified on the same {settings.frames} held-out test frames "
             f"(round-robin over labels), n0 = {settings.n0}, n = {settings.n}, alpha = "
             f"{settings.alpha:g}, {settings.precision}; attack 'sa': SmoothAdv on g "
             f"({settings.attack_steps} steps, {settings.attack_noise_draws} noise draws) at "
             "the budget eps of the row, which is also the budget of the label range. Shares "
             "of frames with their 95 % Clopper-Pearson intervals.", "",
             "| candidate | attack | eps | g accuracy | certified right | certified WRONG | "
             "abstain |", "|---|---|---|---|---|---|---|"]
    for name, rows in results.items():
        for r in rows:
            lines.append(f"| {name} | {r['attack']} | {r['eps']:g} | {r['accuracy']:.3f} | "
                         f"{_share(r, 'certified_right')} | {_share(r, 'certified_wrong')} | "
                         f"{_share(r, 'interval_abstain')} |")
    if tails:
        names = list(next(iter(tails.values())))
        lines += ["", f"Own-label tail: per true label, the share of its frames to which g gives "
                      f"under {TAIL_SHARE:g} of the n votes at the clean frame, with its 95 % "
                      "interval and (in parentheses) the lowest own-label share.", "",
                  "| candidate | " + " | ".join(names) + " |",
                  "|---|" + "---|" * len(names)]
        for cand, tail in tails.items():
            cells = [f"{t['under_half']}/{t['frames']} = {t['share']:.3f} "
                     f"[{t['share_ci95'][0]:.3f}, {t['share_ci95'][1]:.3f}] "
                     f"({t['lowest']:.3f})" for t in tail.values()]
            lines.append(f"| {cand} | " + " | ".join(cells) + " |")
    rank = choice["ranking"]
    by = (f"the thinnest worst-label tail (then the fewest abstentions under {rank['attack']} "
          f"at eps = {rank['eps']:g})" if rank.get("by") == "tail" else
          f"the fewest abstentions under {rank['attack']} at eps = {rank['eps']:g}")
    lines += ["", f"Pick: **{choice['pick']}**, {by} among the candidates whose certified-wrong "
                  "share is in every cell not above the baseline's 95 % upper bound "
                  f"({', '.join(choice['eligible'])})."]
    for name, why in choice["reasons"].items():
        lines.append(f"- {name}: not eligible, {why}.")
    return "\n".join(lines) + "\n"


def plot(results: dict[str, list[dict]], path: str | Path, settings: SweepSettings) -> None:
    """Abstain (x) vs certified wrong (y), one point per candidate and cell, with the 95 %
    intervals as error bars (a row of panels per attack, a column per budget); written
    atomically as PNG."""
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from drake_cert.io import atomic_write_bytes

    cells = [(r["attack"], r["eps"]) for r in next(iter(results.values()))]
    attacks = list(dict.fromkeys(a for a, _ in cells))
    budgets = list(dict.fromkeys(e for _, e in cells))
    fig, axes = plt.subplots(len(attacks), len(budgets), squeeze=False,
                             figsize=(4.2 * len(budgets), 3.6 * len(attacks)))
    markers = "osD^v<>phX"
    for attack, eps in cells:
        ax = axes[attacks.index(attack)][budgets.index(eps)]
        for k, (name, rows) in enumerate(results.items()):
            r = next(r for r in rows if (r["attack"], r["eps"]) == (attack, eps))
            x, y = r["interval_abstain"], r["certified_wrong"]
            xlo, xhi = r["interval_abstain_ci95"]
            ylo, yhi = r["certified_wrong_ci95"]
            ax.errorbar([x], [y], xerr=[[x - xlo], [xhi - x]], yerr=[[y - ylo], [yhi - y]],
                        marker=markers[k % len(markers)], capsize=3, label=name)
        ax.set_title(f"{settings.preset} sigma {settings.sigma:g}: {attack}, eps {eps:g}")
        ax.set_xlabel("abstain (share of frames)")
        ax.set_ylabel("certified WRONG (share of frames)")
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=8)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())


def write_json(path: str | Path, payload: dict) -> None:
    atomic_write_text(path, json.dumps(json_safe(payload), indent=1, allow_nan=False) + "\n")
