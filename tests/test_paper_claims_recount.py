"""An independent recount of every verdict in results/paper/claims.json from frames.csv: its own
csv, numpy and scipy arithmetic, nothing imported from drake_cert, the rules as the claims
read in the paper:

* a share's 95% interval is Clopper-Pearson; two shares differ where their intervals are apart;
* a speed or squared error is compared frame by frame: mean difference, 95% t-interval;
* "holds"/"fails" where the interval lies inside/outside the claimed region, "(not
  significant)" where only the estimate does; "not informative" for a tie of zeros, the same
  speed on every frame, or an EA that does not measurably slow the baseline;
* a claim holds where it holds on every preset and every sigma: the worst verdict counts.
"""

import csv
import json
from collections import defaultdict
from pathlib import Path

import numpy as np
from scipy import stats

PAPER = Path(__file__).resolve().parents[1] / "results" / "paper"
ORDER = ["fails", "fails (not significant)", "not tested", "not informative",
         "holds (not significant)", "holds"]
BEST_SIGMA = {"carla-like": 0.25, "rtk-like": 0.25, "robotcar-like": 0.5}


def load():
    cells = defaultdict(dict)  # (preset, pipeline, attack, eps, sigma) -> {position: row}
    with open(PAPER / "frames.csv", newline="") as f:
        for r in csv.DictReader(f):
            key = (r["preset"], r["pipeline"], r["attack"], float(r["eps"]), float(r["sigma"]))
            cells[key][int(r["position"])] = r
    return cells


CELLS = load()
PRESETS = list(dict.fromkeys(k[0] for k in CELLS))


def cell(preset, pipeline, attack, eps=None, sigma=0.0):
    if attack == "none":  # clean rows: the main budget's clean cell
        eps = min(k[3] for k in CELLS if k[:3] == (preset, pipeline, "none"))
    return CELLS.get((preset, pipeline, attack, eps, sigma), {})


def sigmas(preset, pipeline, attack, eps):
    return sorted(k[4] for k in CELLS if k[:4] == (preset, pipeline, attack, eps))


def cp(k, n):
    lo = stats.beta.ppf(0.025, k, n - k + 1) if k > 0 else 0.0
    hi = stats.beta.ppf(0.975, k + 1, n - k) if k < n else 1.0
    return lo, hi


def count(c, test):
    return sum(test(r) for r in c.values()), len(c)


def left(c):
    return count(c, lambda r: r["left_lane"] == "True")


def right(c):
    return count(c, lambda r: r["predicted"] == r["true_label"])


def verdict(holds, apart):
    return ("holds" if apart else "holds (not significant)") if holds else \
        ("fails" if apart else "fails (not significant)")


def lower(a, b):
    """Share a below share b: direction and Clopper-Pearson intervals apart."""
    (ka, na), (kb, nb) = a, b
    (la, ha), (lb, hb) = cp(ka, na), cp(kb, nb)
    return verdict(ka / na < kb / nb, ha < lb or hb < la)


def diff(a, b, value):
    d = np.array([value(a[k]) - value(b[k]) for k in sorted(set(a) & set(b))])
    half = stats.t.ppf(0.975, len(d) - 1) * d.std(ddof=1) / np.sqrt(len(d))
    return d.mean(), d.mean() - half, d.mean() + half, bool(np.all(d == 0))


def greater(d, strict):
    mean, lo, hi, _ = d
    if strict:
        return verdict(mean > 0, lo > 0 if mean > 0 else hi <= 0)
    return verdict(mean >= 0, lo >= 0 if mean >= 0 else hi < 0)


def speed(r):
    return float(r["velocity_mps"])


def sq_error(r):
    return ((float(r["predicted"]) - float(r["stiffness_n_per_rad"])) / 1e3) ** 2


def worst(vs):
    return min(vs, key=ORDER.index)


def zero(c):
    return "holds" if left(c)[0] == 0 else "fails"


def at_least_as_fast(p, eps, pipe, base):
    slowed = diff(cell(p, base, "none"), cell(p, base, "ea", eps), speed)
    out = []
    for s in sigmas(p, pipe, "ea", eps):
        d = diff(cell(p, pipe, "ea", eps, s), cell(p, base, "ea", eps), speed)
        out.append("not informative" if slowed[1] <= 0 or d[3] else greater(d, strict=False))
    return worst(out)


def less_unstable(p, eps, pipe):
    f = left(cell(p, "f", "sa", eps))
    return worst("not informative" if left(cell(p, pipe, "sa", eps, s))[0] == f[0] == 0
                 else lower(left(cell(p, pipe, "sa", eps, s)), f)
                 for s in sigmas(p, pipe, "sa", eps))


def best_sigma(p, eps, pipe):
    per = {s: left(cell(p, pipe, "sa", eps, s)) for s in sigmas(p, pipe, "sa", eps)}
    fewest = min(k for k, _ in per.values())
    best = [s for s, (k, _) in per.items() if k == fewest]
    if len(best) == len(per):
        return "not informative"

    def apart(a, b):
        (la, ha), (lb, hb) = cp(*a), cp(*b)
        return ha < lb or hb < la
    paper = BEST_SIGMA[p]
    if paper in best:
        return verdict(True, len(best) == 1 and all(apart(per[paper], v) for s, v in per.items()
                                                    if s != paper))
    return verdict(False, apart(per[paper], per[best[0]]))


def h_stable(p, eps, _):
    if left(cell(p, "f_reg", "sa", eps))[0] == 0:
        return "not informative"
    return worst(zero(cell(p, "h", "sa", eps, s)) for s in sigmas(p, "h", "sa", eps))


PER_PRESET = {
    "f_stable_clean": lambda p, e, _: zero(cell(p, "f", "none")),
    "f_accuracy_drops_under_attack": lambda p, e, _: worst(
        lower(right(cell(p, "f", a, e)), right(cell(p, "f", "none"))) for a in ("sa", "ea")),
    "f_unstable_under_sa": lambda p, e, _: lower(left(cell(p, "f", "none")),
                                                 left(cell(p, "f", "sa", e))),
    "f_slower_under_ea": lambda p, e, _: greater(
        diff(cell(p, "f", "none"), cell(p, "f", "ea", e), speed), strict=True),
    "g_less_unstable_than_f_under_sa": less_unstable,
    "sigma_ablation_best_sigma": best_sigma,
    "g_at_least_as_fast_as_f_under_ea": lambda p, e, g: at_least_as_fast(p, e, g, "f"),
    "f_reg_stable_clean": lambda p, e, _: zero(cell(p, "f_reg", "none")),
    "f_reg_unstable_under_sa": lambda p, e, _: lower(left(cell(p, "f_reg", "none")),
                                                     left(cell(p, "f_reg", "sa", e))),
    "f_reg_error_grows_under_attack": lambda p, e, _: worst(greater(diff(
        cell(p, "f_reg", a, e), cell(p, "f_reg", "none"), sq_error), strict=True)
        for a in ("sa", "ea")),
    "f_reg_slower_under_ea": lambda p, e, _: greater(
        diff(cell(p, "f_reg", "none"), cell(p, "f_reg", "ea", e), speed), strict=True),
    "h_stable_under_sa": h_stable,
    "h_at_least_as_fast_as_f_reg_under_ea": lambda p, e, _: at_least_as_fast(p, e, "h",
                                                                             "f_reg"),
}


def rtk_least_vulnerable(eps):
    rtk = left(cell("rtk-like", "f", "sa", eps))
    return [(f"rtk-like vs {p}", "not informative" if rtk[0] == left(cell(p, "f", "sa", eps))[0]
             == 0 else lower(rtk, left(cell(p, "f", "sa", eps))))
            for p in PRESETS if p != "rtk-like"]


def recount(claim, eps, pipe):
    """[(where, verdict)] of one judgement, recounted."""
    if claim == "rtk_least_vulnerable":
        return rtk_least_vulnerable(eps)
    return [(p, PER_PRESET[claim](p, eps, pipe)) for p in PRESETS]


def test_every_verdict_of_claims_json_is_recounted_from_frames_csv():
    stored = json.loads((PAPER / "claims.json").read_text())["paper_claims"]
    assert stored["budget_eps"] == 1.0  # the paper's delta = 255
    judgements = 0
    for c in stored["claims"]:
        for j in [c, *c["secondary"]]:
            mine = recount(c["claim"], j["eps"], j["pipeline"])
            assert [(r["where"], r["verdict"]) for r in j["rows"]] == mine, \
                (c["claim"], j["eps"], j["pipeline"])
            assert j["verdict"] == worst(v for _, v in mine)
            judgements += 1
    assert {c["claim"] for c in stored["claims"]} == set(PER_PRESET) | {"rtk_least_vulnerable"}
    counts = {v: sum(c["verdict"] == v for c in stored["claims"]) for v in ORDER}
    assert stored["counts"] == counts and sum(counts.values()) == 14
    # a main verdict each; eps = 0.25 for the 12 with a budget; g_conformal at both for g's 3
    assert judgements == 14 + 12 + 3 * 2
