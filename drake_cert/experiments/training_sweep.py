"""The training sweep: which classifier certifies the most without certifying wrong more.

For one preset and sigma, each candidate model (the baseline, by default the shipped model, and
those ``drake-cert sweep`` trains: training method x lambda) is certified on the same held-out
test frames, clean and under the stability attack (SmoothAdv on g) at each budget eps, by
:func:`~drake_cert.experiments.perception_eval.certify_classifier`, the function ``drake-cert
certify`` runs. Each cell reports the three outcomes of the run-time label range at eps
(:func:`~drake_cert.experiments.perception_eval.decision_shares`: certified right, certified
wrong, abstain) with 95 % Clopper-Pearson intervals.

The pick (:func:`pick_candidate`, docs/design.md 3.2): among the candidates whose
certified-wrong share is, in every cell, not above the baseline's 95 % upper bound in that
cell, the one that abstains least in the ranking cell (by default the stability attack at
eps = sigma, the drive's budget); the baseline itself always qualifies, so the pick never
certifies wrong more than today's model by more than the baseline's own sampling error.
"""

from __future__ import annotations

import dataclasses
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
    json_safe,
    select_frames,
)
from drake_cert.io import atomic_write_text

OUTCOMES = ("certified_right", "certified_wrong", "interval_abstain")
DATA_SEED = 0  # the synthetic splits the shipped models were trained and tested on


@dataclasses.dataclass(frozen=True)
class Candidate:
    """One model of the sweep: a name, and the ``drake-cert train`` options that make it
    (None: an existing file, e.g. the shipped model)."""

    name: str
    train_options: tuple[str, ...] | None = None


def default_candidates(lambdas: Iterable[float], copies: int = 2,
                       eta: float = 0.5) -> list[Candidate]:
    """The baseline (an existing file: by default the shipped model) and consistency
    regularization at each lambda."""
    out = [Candidate("baseline")]
    for lam in lambdas:
        if not (math.isfinite(lam) and lam >= 0):
            raise ConfigError(f"lambda {lam} must be a finite number >= 0")
        out.append(Candidate(f"consistency_l{lam:g}",
                             ("--method", "consistency", "--consistency-lambda", f"{lam:g}",
                              "--consistency-eta", f"{eta:g}", "--copies", str(copies))))
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

    def __post_init__(self):
        if self.sigma <= 0:
            raise ConfigError("the sweep compares smoothed classifiers: sigma must be > 0")
        if not self.budgets or any(not (math.isfinite(e) and e >= 0) for e in self.budgets):
            raise ConfigError(f"budgets {self.budgets} must be finite numbers >= 0")
        if self.rank_attack not in self.attacks or self.ranking_eps not in self.budgets:
            raise ConfigError(f"the ranking cell ({self.rank_attack}, eps "
                              f"{self.ranking_eps:g}) is not among the cells evaluated")

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
                       progress: Callable[[Iterable], Iterable] | None = None) -> list[dict]:
    """One row per (attack, eps) cell: the model's three outcome shares on the sweep's frames
    (the clean certificates are computed once and shared by the cells)."""
    index = select_frames(test.labels, settings.frames, frame_choice_seed(settings.seed))
    images, labels = test.images[index], test.labels[index]
    stiffness = test.stiffness_n_per_rad[index]
    clean_cache: dict = {}
    rows = []
    for attack in settings.attacks:
        for eps in settings.budgets:
            cs = settings.certify_settings(attack, eps)
            _, summary = certify_classifier(
                model, EvalFrames(images, labels, stiffness, tuple(test.label_names)), table,
                cs, progress, CalibrationInputs(clean_cache=clean_cache))
            row = {"attack": attack, "eps": eps, "frames": summary["frames"],
                   "accuracy": summary["accuracy"]}
            for name in OUTCOMES:
                row[name] = summary[f"{name}_rate"]
                row[f"{name}_ci95"] = summary[f"{name}_rate_ci95"]
            rows.append(row)
    return rows


def pick_candidate(results: dict[str, list[dict]], settings: SweepSettings,
                   baseline: str = "baseline") -> dict:
    """The candidate to ship (module docstring): ``{"pick", "eligible", "reasons"}``, where
    ``reasons[name]`` says why a candidate was not eligible."""
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

    best = min(eligible, key=lambda name: (abstain(name), name != baseline))
    return {"pick": best, "eligible": eligible, "reasons": reasons,
            "ranking": {"attack": settings.rank_attack, "eps": settings.ranking_eps}}


def _share(row: dict, name: str) -> str:
    lo, hi = row[f"{name}_ci95"]
    return f"{row[name]:.3f} [{lo:.3f}, {hi:.3f}]"


def render(results: dict[str, list[dict]], choice: dict, settings: SweepSettings,
           header: Iterable[str] = ()) -> str:
    """Markdown of the sweep: one row per candidate and cell, and the pick with its reason."""
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
    rank = choice["ranking"]
    lines += ["", f"Pick: **{choice['pick']}**, the fewest abstentions under {rank['attack']} "
                  f"at eps = {rank['eps']:g} among the candidates whose certified-wrong share "
                  "is in every cell not above the baseline's 95 % upper bound "
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
