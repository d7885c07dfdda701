"""The paper's claims, judged as a referee would: one verdict per claim at the paper's budget.

:func:`paper_claims` returns what ``claims.json`` stores under ``paper_claims``: ``claims``, one
entry per checkable claim of the paper's text and tables (:data:`CLAIMS`), each with

* ``verdict``: its one verdict at the paper's budget, eps = :data:`PAPER_BUDGET_EPS` (its
  delta = 255 read as an L2 norm over [0, 255] pixel values, docs/design.md 7.1), for a claim
  about g with the paper's safe-set interval (pipeline ``g``). A claim is judged on ``rows``,
  one per preset (per pair of presets for a claim that compares them), and holds where it holds
  on every row: the verdict is the worst of the rows' (:func:`worst`); a claim made at every
  sigma (the paper's tables give each sigma) is judged the same way over its sigmas;
* ``rows``: ``where`` (the preset), ``verdict``, ``figures`` (the statistic, the comparison and
  its 95% interval) and ``text`` (the same in a few words);
* ``paper``: the paper's own figures per preset, their unit named, at the paper's budget only;
* ``secondary``: the same claim at eps = 0.25 and, for g, read by the robust conformal interval
  (``g_conformal``): shown under the verdict, never counted.

It also holds ``counts`` (:func:`verdict_counts`), ``method`` (the intervals, in words) and
``ea_attack_strength`` (:func:`ea_attack_strength`: how much the efficiency attack moves f).

Verdicts (:data:`VERDICTS`, worst first): "holds" and "fails" where the 95% uncertainty lies
wholly inside or wholly outside the claimed region; "holds (not significant)" and "fails (not
significant)" where only the point estimate says so; "not informative" where the comparison
cannot tell: a tie of zeros, the same value on every frame, or an attack that does not
measurably move the baseline the claim is compared against; "not tested" where the run holds
no rows for it. Uncertainty: a share carries its two-sided 95% Clopper-Pearson interval and
two shares are apart where their intervals do not overlap; a speed or a squared error is
compared frame by frame (the two episodes of the same test frame), by the mean of the per-frame
differences and its two-sided 95% Student t-interval (n - 1 degrees of freedom). Both treat
the test frames as a random sample; no seed is involved.

The project's own criteria (zero instability inside certificates, 80% of the clean speed kept)
are not here: :mod:`drake_cert.experiments.claims` checks them and labels them as ours.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import numpy as np
from scipy.stats import t as student_t

from drake_cert.experiments.perception_eval import clopper_pearson_interval
from drake_cert.experiments.reproduce_config import PAPER_BUDGET_EPS, PAPER_UNITS

SECONDARY_EPS = (0.25,)  # the main tables' budget: secondary rows under each verdict
G_PIPELINES = ("g", "g_conformal")  # the paper's interval first: its verdict
PRESETS = ("carla-like", "rtk-like", "robotcar-like")  # the paper's Carla, RTK, RobotCar

HOLDS, HOLDS_NS = "holds", "holds (not significant)"
FAILS, FAILS_NS = "fails", "fails (not significant)"
NOT_INFORMATIVE, NOT_TESTED = "not informative", "not tested"
VERDICTS = (FAILS, FAILS_NS, NOT_TESTED, NOT_INFORMATIVE, HOLDS_NS, HOLDS)  # worst first

METHOD = ("shares: two-sided 95% Clopper-Pearson interval, two shares apart where their "
          "intervals do not overlap; speeds and squared errors: mean of the per-frame "
          "differences (the same test frame's two episodes) with its two-sided 95% Student "
          "t-interval; a claim holds where it holds on every preset (and every sigma it is "
          "made at): its verdict is the worst of theirs, in the order " + ", ".join(VERDICTS))

# The paper's best sigma against the safety attack (Section VI's ablation of Table III).
PAPER_BEST_SIGMA = {"carla-like": 0.25, "rtk-like": 0.25, "robotcar-like": 0.5}

# Units of the paper's figures, named where they stand (the paper defines neither its
# instability, which reaches 200.00 and is no share, nor its velocity's or MSE's unit).
_INSTABILITY = PAPER_UNITS["instability"]
_VELOCITY = PAPER_UNITS["velocity_mps"]


def share(hits: int, total: int) -> dict:
    """``hits`` of ``total`` as a share in % with its two-sided 95% Clopper-Pearson interval."""
    if total == 0:
        return dict(hits=0, total=0, pct=math.nan, ci95_pct=[0.0, 100.0])
    lo, hi = clopper_pearson_interval(hits, total)
    return dict(hits=hits, total=total, pct=100.0 * hits / total,
                ci95_pct=[100.0 * lo, 100.0 * hi])


def paired_difference(a: dict[int, float], b: dict[int, float]) -> dict:
    """Mean of ``a[k] - b[k]`` over the frames ``k`` both hold, with its two-sided 95% Student
    t-interval (n - 1 degrees of freedom; no interval below two frames); ``identical``: the
    difference is 0 on every frame."""
    keys = sorted(set(a) & set(b))
    d = np.array([a[k] - b[k] for k in keys], dtype=float)
    if len(d) == 0:
        return dict(frames=0, mean=math.nan, ci95=[-math.inf, math.inf], identical=False)
    half = (student_t.ppf(0.975, len(d) - 1) * d.std(ddof=1) / math.sqrt(len(d))
            if len(d) > 1 else math.inf)
    mean = float(d.mean())
    return dict(frames=len(d), mean=mean, ci95=[mean - half, mean + half],
                identical=bool(np.all(d == 0)))


def worst(verdicts) -> str:
    """The worst of ``verdicts`` in :data:`VERDICTS` order (a claim holds where every part
    holds); "not tested" for none."""
    return min(verdicts, key=VERDICTS.index, default=NOT_TESTED)


def _verdict(holds: bool, apart: bool) -> str:
    return (HOLDS if apart else HOLDS_NS) if holds else (FAILS if apart else FAILS_NS)


def interval_verdict(diff: dict, strict: bool) -> str:
    """The claim "the difference is > 0" (``strict``) or ">= 0" judged on :func:`paired_difference`:
    apart where the 95% interval lies wholly inside the claimed region or wholly outside it."""
    lo, hi = diff["ci95"]
    if strict:
        return _verdict(diff["mean"] > 0, lo > 0 if diff["mean"] > 0 else hi <= 0)
    return _verdict(diff["mean"] >= 0, lo >= 0 if diff["mean"] >= 0 else hi < 0)


def _apart(a: dict, b: dict) -> bool:
    """Whether the 95% intervals of two shares do not overlap (either way round)."""
    return a["total"] > 0 and b["total"] > 0 and (
        a["ci95_pct"][1] < b["ci95_pct"][0] or b["ci95_pct"][1] < a["ci95_pct"][0])


def share_verdict(lower: dict, higher: dict) -> str:
    """The claim "share ``lower`` < share ``higher``" (shares of :func:`share`)."""
    return _verdict(lower["pct"] < higher["pct"], _apart(lower, higher))


def _row(verdict: str, text: str, **figures) -> dict:
    return dict(verdict=verdict, figures=figures, text=text)


def _missing(what: str) -> dict:
    return _row(NOT_TESTED, f"the run has no {what} at this budget")


# -- reading a preset's rows --------------------------------------------------------------

def _claim_cell(mine: list[dict], pipeline: str, attack: str, eps=None, sigma=None) -> list[dict]:
    """One cell's rows as a claim reads them: an attacked cell at ``eps``; a clean cell at any
    budget, the first one the run holds (clean rows repeat per budget). Unlike
    ``claims._cell``, whose ``eps=None`` takes every budget."""
    cell = [r for r in mine if r["pipeline"] == pipeline and r["attack"] == attack
            and (sigma is None or r["sigma"] == sigma)]
    if attack == "none":
        first = min((r["eps"] for r in cell), default=None)
        return [r for r in cell if r["eps"] == first]
    return [r for r in cell if r["eps"] == eps]


def _sigmas(mine: list[dict], pipeline: str, attack: str, eps: float) -> list[float]:
    return sorted({r["sigma"] for r in mine if r["pipeline"] == pipeline
                   and r["attack"] == attack and r["eps"] == eps})


def _left(rows: list[dict]) -> dict:
    return share(sum(bool(r["left_lane"]) for r in rows), len(rows))


def _right(rows: list[dict]) -> dict:
    return share(sum(r["predicted"] == r["true_label"] for r in rows), len(rows))


def _speeds(rows: list[dict]) -> dict[int, float]:
    return {r["position"]: float(r["velocity_mps"]) for r in rows}


def _sq_errors_kn2(rows: list[dict]) -> dict[int, float]:
    return {r["position"]: ((float(r["predicted"]) - r["stiffness_n_per_rad"]) / 1e3) ** 2
            for r in rows}


def _mean(values: dict[int, float]) -> float:
    return float(np.mean(list(values.values()))) if values else math.nan


def _pct(s: dict) -> str:
    lo, hi = s["ci95_pct"]
    return f"{s['hits']}/{s['total']} = {s['pct']:.1f}% [{lo:.1f}, {hi:.1f}]"


def _diff(d: dict, unit: str = "") -> str:
    lo, hi = d["ci95"]
    return f"{d['mean']:+.2f}{' ' + unit if unit else ''} [{lo:+.2f}, {hi:+.2f}]"


# -- the claims' tests: (a preset's rows, budget or None, g pipeline or None) -> one row
# (:func:`_row`: verdict, text, figures); a claim across presets takes every preset's rows
# and returns one row per pair.

def _zero(s: dict) -> str:
    """A claim of no departure at all: one departure refutes it (its interval excludes 0)."""
    return HOLDS if s["hits"] == 0 else FAILS


def f_stable_clean(mine, _eps, _pipe, pipeline="f"):
    """``pipeline`` never leaves its lane without attack."""
    clean = _left(_claim_cell(mine, pipeline, "none"))
    if not clean["total"]:
        return _missing(f"{pipeline} clean rows")
    return _row(_zero(clean), f"left clean {_pct(clean)}", clean_left_lane=clean)


def f_accuracy_drops(mine, eps, _pipe):
    """f's share of frames labelled right under SA and under EA each below the clean share."""
    clean = _right(_claim_cell(mine, "f", "none"))
    sa, ea = (_right(_claim_cell(mine, "f", a, eps)) for a in ("sa", "ea"))
    if not (clean["total"] and sa["total"] and ea["total"]):
        return _missing("f rows clean and under both attacks")
    return _row(worst([share_verdict(sa, clean), share_verdict(ea, clean)]),
                f"right clean {_pct(clean)}, SA {_pct(sa)}, EA {_pct(ea)}",
                clean_accuracy=clean, sa_accuracy=sa, ea_accuracy=ea)


def f_unstable_under_sa(mine, eps, _pipe, pipeline="f"):
    """``pipeline``'s share of SA episodes that left the lane above its clean share."""
    clean = _left(_claim_cell(mine, pipeline, "none"))
    sa = _left(_claim_cell(mine, pipeline, "sa", eps))
    if not clean["total"] or not sa["total"]:
        return _missing(f"{pipeline} rows clean and under SA")
    return _row(share_verdict(clean, sa), f"left clean {_pct(clean)}, SA {_pct(sa)}",
                clean_left_lane=clean, sa_left_lane=sa)


def slowdown(mine: list[dict], pipeline: str, eps: float) -> dict:
    """How much EA at ``eps`` slows ``pipeline`` (sigma 0): clean minus EA speed per frame
    (:func:`paired_difference`, m/s) with both mean speeds."""
    clean = _speeds(_claim_cell(mine, pipeline, "none"))
    ea = _speeds(_claim_cell(mine, pipeline, "ea", eps))
    return dict(paired_difference(clean, ea), clean_mps=_mean(clean), ea_mps=_mean(ea))


def f_slower_under_ea(mine, eps, _pipe, pipeline="f"):
    """``pipeline``'s EA speed below its clean speed, frame by frame (:func:`slowdown` > 0)."""
    slow = slowdown(mine, pipeline, eps)
    if not slow["frames"]:
        return _missing(f"{pipeline} rows clean and under EA")
    return _row(interval_verdict(slow, strict=True),
                f"{slow['clean_mps']:.2f} -> {slow['ea_mps']:.2f} m/s, slower by "
                f"{_diff(slow, 'm/s')}", slowdown_mps=slow)


def rtk_least_vulnerable(rows, eps, _pipe):
    """Across presets: f's SA departure share on rtk-like below each other preset's."""
    left = {p: _left(_claim_cell([r for r in rows if r["preset"] == p], "f", "sa", eps))
            for p in dict.fromkeys(r["preset"] for r in rows)}
    if not left.get("rtk-like", {}).get("total") or len(left) < 2:
        return [dict(where="rtk-like", **_missing("f rows under SA on rtk-like and another "
                                                  "preset"))]
    rtk = left.pop("rtk-like")
    return [dict(where=f"rtk-like vs {p}", **_row(
        NOT_INFORMATIVE if rtk["hits"] == s["hits"] == 0 else share_verdict(rtk, s),
        f"left under SA: rtk-like {_pct(rtk)}, {p} {_pct(s)}", rtk_sa_left_lane=rtk,
        other_sa_left_lane=s)) for p, s in left.items()]


def g_less_unstable(mine, eps, pipe, baseline="f"):
    """At every sigma, ``pipe``'s SA departure share below ``baseline``'s (every SA episode:
    an abstention drives the envelope); a tie of zeros is not informative."""
    base = _left(_claim_cell(mine, baseline, "sa", eps))
    sigmas = _sigmas(mine, pipe, "sa", eps)
    if not base["total"] or not sigmas:
        return _missing(f"{baseline} and {pipe} rows under SA")
    per = {s: _left(_claim_cell(mine, pipe, "sa", eps, s)) for s in sigmas}
    by = {f"{s:g}": dict(g, verdict=NOT_INFORMATIVE if g["hits"] == base["hits"] == 0
                         else share_verdict(g, base)) for s, g in per.items()}
    return _row(worst(v["verdict"] for v in by.values()),
                f"left under SA: {baseline} {_pct(base)}; {pipe} " + "; ".join(
                    f"sigma {s} {_pct(v)}: {v['verdict']}" for s, v in by.items()),
                baseline_sa_left_lane=base, sa_left_lane_by_sigma=by)


def best_sigma(mine, eps, pipe):
    """The paper's best sigma (:data:`PAPER_BEST_SIGMA`) among those with the fewest SA
    departures of ``pipe``; not informative where every sigma has as many."""
    sigmas = _sigmas(mine, pipe, "sa", eps)
    paper = PAPER_BEST_SIGMA.get(mine[0]["preset"])
    if len(sigmas) < 2 or paper not in sigmas:
        return _missing(f"{pipe} under SA at two or more sigmas, the paper's best among them")
    per = {s: _left(_claim_cell(mine, pipe, "sa", eps, s)) for s in sigmas}
    fewest = min(v["hits"] for v in per.values())
    best = [s for s, v in per.items() if v["hits"] == fewest]
    text = (f"fewest SA departures at sigma {' / '.join(f'{s:g}' for s in best)} (the paper's "
            f"{paper:g}); " + "; ".join(f"sigma {s:g} {_pct(v)}" for s, v in per.items()))
    figures = dict(paper_best_sigma=paper, best_sigmas=best,
                   sa_left_lane_by_sigma={f"{s:g}": v for s, v in per.items()})
    if len(best) == len(per):
        return _row(NOT_INFORMATIVE, text, **figures)
    if paper in best:  # apart: the paper's sigma alone fewest, its interval apart from each
        apart = len(best) == 1 and all(_apart(per[paper], v) for s, v in per.items()
                                       if s != paper)
        return _row(_verdict(True, apart), text, **figures)
    return _row(_verdict(False, _apart(per[paper], per[best[0]])), text, **figures)


def g_at_least_as_fast(mine, eps, pipe, baseline="f"):
    """At every sigma, ``pipe``'s EA speed at least ``baseline``'s, frame by frame; not
    informative where EA does not measurably slow the baseline (the interval of its slowdown
    reaches 0) or where both drive the same speed on every frame."""
    slow = slowdown(mine, baseline, eps)
    sigmas = _sigmas(mine, pipe, "ea", eps)
    if not slow["frames"] or not sigmas:
        return _missing(f"{baseline} (clean and under EA) and {pipe} rows under EA")
    base = _speeds(_claim_cell(mine, baseline, "ea", eps))
    moved = slow["ci95"][0] > 0
    by = {}
    for s in sigmas:
        cell = _claim_cell(mine, pipe, "ea", eps, s)
        d = paired_difference(_speeds(cell), base)
        by[f"{s:g}"] = dict(d, ea_mps=_mean(_speeds(cell)),
                            certified=sum(bool(r["certified"]) for r in cell),
                            verdict=interval_verdict(d, strict=False)
                            if moved and not d["identical"] else NOT_INFORMATIVE)
    return _row(worst(v["verdict"] for v in by.values()),
                f"{baseline} {slow['clean_mps']:.2f} clean -> {slow['ea_mps']:.2f} m/s under "
                f"EA (slower by {_diff(slow, 'm/s')}); {pipe} under EA minus {baseline}: "
                + "; ".join(f"sigma {s} {v['ea_mps']:.2f} m/s, {_diff(v, 'm/s')} "
                            f"({v['certified']} certified): {v['verdict']}"
                            for s, v in by.items()),
                baseline_slowdown_mps=slow, ea_minus_baseline_by_sigma=by)


def f_reg_stable_clean(mine, eps, pipe):
    """:func:`f_stable_clean` for f_reg."""
    return f_stable_clean(mine, eps, pipe, pipeline="f_reg")


def f_reg_unstable_under_sa(mine, eps, pipe):
    """:func:`f_unstable_under_sa` for f_reg."""
    return f_unstable_under_sa(mine, eps, pipe, pipeline="f_reg")


def f_reg_slower_under_ea(mine, eps, pipe):
    """:func:`f_slower_under_ea` for f_reg."""
    return f_slower_under_ea(mine, eps, pipe, pipeline="f_reg")


def f_reg_error_grows(mine, eps, _pipe):
    """f_reg's squared stiffness error ((kN/rad)^2) under SA and under EA each above the clean
    one, frame by frame."""
    clean = _sq_errors_kn2(_claim_cell(mine, "f_reg", "none"))
    grows = {a: paired_difference(_sq_errors_kn2(_claim_cell(mine, "f_reg", a, eps)), clean)
             for a in ("sa", "ea")}
    if not all(d["frames"] for d in grows.values()):
        return _missing("f_reg rows clean and under both attacks")
    return _row(worst(interval_verdict(d, strict=True) for d in grows.values()),
                f"clean {_mean(clean):.0f} (kN/rad)^2; SA minus clean "
                f"{_diff(grows['sa'])}, EA minus clean {_diff(grows['ea'])}",
                clean_sq_error_kn2=_mean(clean), sa_growth_kn2=grows["sa"],
                ea_growth_kn2=grows["ea"])


def h_stable_under_sa(mine, eps, _pipe):
    """No SA episode of h leaves its lane, at every sigma; not informative where SA moves no
    f_reg episode out of its lane either."""
    base = _left(_claim_cell(mine, "f_reg", "sa", eps))
    sigmas = _sigmas(mine, "h", "sa", eps)
    if not base["total"] or not sigmas:
        return _missing("f_reg and h rows under SA")
    by = {f"{s:g}": dict(_left(_claim_cell(mine, "h", "sa", eps, s)), certified=sum(
        bool(r["certified"]) for r in _claim_cell(mine, "h", "sa", eps, s))) for s in sigmas}
    verdict = worst(_zero(v) for v in by.values()) if base["hits"] else NOT_INFORMATIVE
    return _row(verdict, f"left under SA: f_reg {_pct(base)}; h " + "; ".join(
        f"sigma {s} {_pct(v)} ({v['certified']} certified)" for s, v in by.items()),
        f_reg_sa_left_lane=base, sa_left_lane_by_sigma=by)


def h_at_least_as_fast(mine, eps, _pipe):
    """:func:`g_at_least_as_fast` for h against f_reg."""
    return g_at_least_as_fast(mine, eps, "h", baseline="f_reg")


@dataclasses.dataclass(frozen=True)
class Claim:
    """One claim of the paper: what it says and where (``statement``, ``cite``: the paper's
    table and section numbers), the rule a verdict applies, its test, whether it is made at an
    attack budget, whether it is about g (judged per g pipeline), and whether it compares
    presets (its test then takes every preset's rows and returns one row per pair)."""

    statement: str
    cite: str
    rule: str
    test: Callable
    budgeted: bool = True
    about_g: bool = False
    across_presets: bool = False


CLAIMS = {
    "f_stable_clean": Claim(
        "f never leaves its lane without attack", "Table II: instability 0.00",
        "no clean f episode left the lane", f_stable_clean, budgeted=False),
    "f_accuracy_drops_under_attack": Claim(
        "f's accuracy drops significantly under attack",
        "Tables II and V; Section VI: 'accuracy ... dropped significantly'",
        "f's accuracy under SA and under EA each below its clean accuracy", f_accuracy_drops),
    "f_unstable_under_sa": Claim(
        "f leaves its lane more under SA than clean", "Tables II and V",
        "share of f's SA episodes that left the lane above the clean share",
        f_unstable_under_sa),
    "f_slower_under_ea": Claim(
        "f drives slower under EA than clean",
        "Tables II and V; Section VI: 'significantly hurts the driving efficiency'",
        "f's EA speed below its clean speed, frame by frame", f_slower_under_ea),
    "rtk_least_vulnerable": Claim(
        "RTK is the least vulnerable data set",
        "Section VI: 'RTK dataset is the least vulnerable dataset', with Table V's instability",
        "f's share of SA episodes that left the lane on rtk-like below each other preset's",
        rtk_least_vulnerable, across_presets=True),
    "g_less_unstable_than_f_under_sa": Claim(
        "g leaves its lane less than f under SA, at every sigma",
        "Tables III and V; Section VI", "at every sigma, the share of g's SA episodes (all of "
        "them: an abstention drives the envelope) that left the lane below f's",
        g_less_unstable, about_g=True),
    "sigma_ablation_best_sigma": Claim(
        "the best sigma against SA is 0.25 (Carla), 0.25 (RTK), 0.5 (RobotCar)",
        "Section VI, on Table III", "the paper's best sigma among those with the fewest SA "
        "departures of g", best_sigma, about_g=True),
    "g_at_least_as_fast_as_f_under_ea": Claim(
        "g drives at least as fast as f under EA, at every sigma",
        "Tables IV and V; Section VI: 'the efficiency of A(zeta(g)) is increased by using g'",
        "at every sigma, g's EA speed minus f's, frame by frame, >= 0; not informative where "
        "EA does not measurably slow f", g_at_least_as_fast, about_g=True),
    "f_reg_stable_clean": Claim(
        "f_reg never leaves its lane without attack", "Table VIII: instability 0.0",
        "no clean f_reg episode left the lane", f_reg_stable_clean, budgeted=False),
    "f_reg_unstable_under_sa": Claim(
        "f_reg leaves its lane more under SA than clean", "Tables VIII and IX",
        "share of f_reg's SA episodes that left the lane above the clean share",
        f_reg_unstable_under_sa),
    "f_reg_error_grows_under_attack": Claim(
        "f_reg's squared error grows under attack",
        "Tables VIII and IX; Section VI: 'the MSE increases'",
        "f_reg's squared stiffness error under SA and under EA each above the clean one, frame "
        "by frame", f_reg_error_grows),
    "f_reg_slower_under_ea": Claim(
        "f_reg drives slower under EA than clean",
        "Tables VIII and IX; Section VI: 'performance decreases significantly'",
        "f_reg's EA speed below its clean speed, frame by frame", f_reg_slower_under_ea),
    "h_stable_under_sa": Claim(
        "h never leaves its lane under SA, at every sigma", "Table VII: instability 0.0",
        "no SA episode of h left the lane, at every sigma; not informative where SA moves no "
        "f_reg episode out of its lane", h_stable_under_sa),
    "h_at_least_as_fast_as_f_reg_under_ea": Claim(
        "h drives at least as fast as f_reg under EA, at every sigma",
        "Tables VII and IX; Section VI: 'guarantees the stability and efficiency'",
        "at every sigma, h's EA speed minus f_reg's, frame by frame, >= 0; not informative "
        "where EA does not measurably slow f_reg or both drive the same speed on every frame",
        h_at_least_as_fast),
}

# The paper's figures behind a claim at its delta = 255: their unit, and per preset (Carla,
# RTK, RobotCar) the figures, or one text for a claim across presets.
_PAPER_FIGURES = {
    "f_stable_clean": (f"Table II's instability, {_INSTABILITY}, 0 = none",
                       ("0.00", "0.00", "0.00")),
    "f_accuracy_drops_under_attack": (
        "accuracy, % of frames, clean (Table II) -> attacked (Table V, the attack not named)",
        ("98.6 -> 0", "94.2 -> 80", "95.6 -> 69")),
    "f_unstable_under_sa": (f"instability ({_INSTABILITY}), clean -> SA",
                            ("0.00 -> 200.00", "0.00 -> 37.50", "0.00 -> 61.50")),
    "f_slower_under_ea": (f"velocity ({_VELOCITY}), clean -> EA",
                          ("29.42 -> 27.36", "28.45 -> 27.83", "28.46 -> 25.35")),
    "rtk_least_vulnerable": (f"instability under SA ({_INSTABILITY})",
                             "Carla 200.00, RTK 37.50, RobotCar 61.50"),
    "g_less_unstable_than_f_under_sa": (
        f"instability under SA ({_INSTABILITY}): f, g at sigma 0.25 / 0.5 / 1",
        ("200.00, 6.36 / 12.50 / 25.00", "37.50, 18.99 / 22.50 / 29.30",
         "61.50, 23.29 / 6.82 / 19.13")),
    "sigma_ablation_best_sigma": ("sigma", ("0.25", "0.25", "0.5")),
    "g_at_least_as_fast_as_f_under_ea": (
        f"velocity under EA ({_VELOCITY}): f, g at sigma 0.25 / 0.5 / 1",
        ("27.36, 29.41 / 29.41 / 29.42", "27.83, 28.13 / 28.10 / 28.22",
         "25.35, 27.64 / 28.12 / 28.01")),
    "f_reg_stable_clean": (f"Table VIII's instability ({_INSTABILITY}, 0 = none)",
                           ("0.0", "0.0", "0.0")),
    "f_reg_unstable_under_sa": (f"instability ({_INSTABILITY}), clean -> SA",
                                ("0.0 -> 200.00",) * 3),
    "f_reg_error_grows_under_attack": ("MSE, unit not stated (ours (kN/rad)^2), clean -> "
                                       "attacked", ("0.008 -> 0.44", "0.017 -> 0.43",
                                                    "0.016 -> 0.45")),
    "f_reg_slower_under_ea": (f"velocity ({_VELOCITY}), clean -> EA",
                              ("16.82 -> 16.32", "16.01 -> 15.64", "16.03 -> 15.04")),
    "h_stable_under_sa": (f"Table VII's instability ({_INSTABILITY}, 0 = none) at sigma "
                          "0.25 / 0.5 / 1", ("0.0 / 0.0 / 0.0",) * 3),
    "h_at_least_as_fast_as_f_reg_under_ea": (
        f"velocity ({_VELOCITY}): f_reg under EA, h at sigma 0.25 / 0.5 / 1 (the attack on h "
        "not stated)", ("16.32, 16.78 / 16.79 / 16.65", "15.64, 15.97 / 15.93 / 15.83",
                        "15.04, 16.00 / 15.99 / 15.89")),
}


def judge(name: str, rows: list[dict], eps: float | None, pipeline: str | None) -> dict:
    """Claim ``name`` on ``rows`` at budget ``eps`` (None: a clean claim) for ``pipeline`` (a
    g pipeline, or None): its ``rows`` (one per preset, or per pair of presets) and their
    worst verdict."""
    claim = CLAIMS[name]
    if claim.across_presets:
        out = claim.test(rows, eps, pipeline)
    else:
        out = [dict(where=p, **claim.test([r for r in rows if r["preset"] == p], eps,
                                          pipeline))
               for p in dict.fromkeys(r["preset"] for r in rows)]
    return dict(eps=eps, pipeline=pipeline, verdict=worst(r["verdict"] for r in out),
                rows=out)


def _paper(name: str, rows: list[dict]) -> dict:
    """The paper's figures behind claim ``name``: ``unit`` and ``figures``, per preset of
    ``rows`` the paper has (one text for a claim across presets)."""
    unit, figures = _PAPER_FIGURES[name]
    if isinstance(figures, str):
        return dict(unit=unit, figures=figures)
    presets = [p for p in dict.fromkeys(r["preset"] for r in rows) if p in PRESETS]
    return dict(unit=unit, figures={p: figures[PRESETS.index(p)] for p in presets})


def paper_claims(rows: list[dict], main_eps: float = PAPER_BUDGET_EPS,
                 secondary_eps=SECONDARY_EPS) -> dict:
    """Every claim of :data:`CLAIMS` judged on frame ``rows`` (module docstring): its verdict
    at ``main_eps`` with ``g``, then secondary judgements at ``secondary_eps`` and with
    ``g_conformal`` (the pipelines the rows hold)."""
    held = {r["pipeline"] for r in rows}
    out = []
    for name, claim in CLAIMS.items():
        pipes = ([p for p in G_PIPELINES if p in held] or ["g"]) if claim.about_g else [None]
        budgets = [main_eps, *(e for e in secondary_eps if e != main_eps)] \
            if claim.budgeted else [None]
        judged = [judge(name, rows, e, p) for p in pipes for e in budgets]
        main = judged.pop(0)
        out.append(dict(claim=name, statement=claim.statement, cite=claim.cite,
                        rule=claim.rule, **main,
                        paper=_paper(name, rows) if main_eps == PAPER_BUDGET_EPS else {},
                        secondary=judged))
    return dict(budget_eps=main_eps, method=METHOD, counts=verdict_counts(out), claims=out,
                ea_attack_strength=ea_attack_strength(rows))


def ea_attack_strength(rows: list[dict]) -> list[dict]:
    """Per preset, how much the efficiency attack moves f at each budget the run holds: f's
    clean speed and accuracy; per budget its EA speed, slowdown (:func:`slowdown`), accuracy
    and the share of the largest slowdown a label flip can cause (down to f's slowest speed on
    any frame, the design of the preset's least grippy label, on every frame)."""
    out = []
    for preset in dict.fromkeys(r["preset"] for r in rows):
        mine = [r for r in rows if r["preset"] == preset and r["pipeline"] == "f"]
        if not mine:
            continue
        clean = _claim_cell(mine, "f", "none")
        floor = min(float(r["velocity_mps"]) for r in mine)
        budgets = sorted({r["eps"] for r in mine if r["attack"] == "ea"})
        possible = _mean(_speeds(clean)) - floor
        by = {}
        for e in budgets:
            slow = slowdown(mine, "f", e)
            by[f"{e:g}"] = dict(slowdown_mps=slow, accuracy=_right(_claim_cell(mine, "f", "ea", e)),
                                of_possible=slow["mean"] / possible if possible > 0
                                else math.nan)
        out.append(dict(preset=preset, clean_mps=_mean(_speeds(clean)),
                        clean_accuracy=_right(clean), floor_mps=floor, ea_by_eps=by))
    return out


def verdict_counts(claims: list[dict]) -> dict:
    """How many claims have each main verdict (the secondary rows are not counted)."""
    return {v: sum(c["verdict"] == v for c in claims) for v in VERDICTS}


def counts_text(counts: dict) -> str:
    """The verdict counts in words, worst first: "4 fails, ..., 7 holds" (the README's)."""
    return ", ".join(f"{n} {v}" for v, n in counts.items() if n)


def failing(document: dict) -> list[str]:
    """One line per claim whose verdict is not a hold: its statement, citation, verdict and
    the presets behind it, in :data:`CLAIMS` order; the README quotes these."""
    lines = []
    for c in document["claims"]:
        if c["verdict"] in (HOLDS, HOLDS_NS):
            continue
        where = [r["where"] for r in c["rows"] if r["verdict"] == c["verdict"]]
        lines.append(f"{c['statement']} ({c['cite']}): {c['verdict']} on {', '.join(where)}")
    return lines


def _budget(eps) -> str:
    return "clean" if eps is None else f"eps = {eps:g}"


def _cells(judged: dict, presets: list[str]) -> list[str]:
    """One cell per preset: its verdict and figures (a claim across presets: its pairs)."""
    by = {r["where"]: r for r in judged["rows"]}
    if not all(p in by for p in presets):  # a claim across presets: every pair in one cell
        return ["; ".join(f"{r['where']}: {r['verdict']}: {r['text']}" for r in judged["rows"])
                ] + [""] * (len(presets) - 1)
    return [f"{by[p]['verdict']}: {by[p]['text']}" for p in presets]


def _paper_text(paper: dict) -> str:
    if not paper:
        return "-"
    figures = paper["figures"]
    if isinstance(figures, dict):
        figures = "; ".join(f"{p}: {v}" for p, v in figures.items())
    return f"{figures}. Unit: {paper['unit']}"


def markdown(document: dict) -> str:
    """``claims.md``'s section on the paper's claims: the counts, the method, one table with a
    row per claim (its verdict at the paper's budget, per preset, the paper's figure with its
    unit) and its secondary rows under it, then the efficiency attack's strength."""
    claims = document["claims"]
    presets = list(dict.fromkeys(r["where"] for c in claims for r in c["rows"]
                                 if not CLAIMS[c["claim"]].across_presets))
    counts = counts_text(document["counts"])
    eps = document["budget_eps"]
    lines = [f"{len(claims)} claims of the paper's text and tables, one verdict each at the "
             f"paper's budget (eps = {eps:g}, its delta = 255) and, for g, with the paper's "
             f"safe-set interval: {counts}. The rows marked 'secondary' (eps = 0.25; g read by "
             f"the robust conformal interval) are shown, not counted. Method: {METHOD}. The "
             "paper's figures stand in their own column with their unit, at the paper's "
             "budget only: its instability is not a share and its velocity has no stated "
             "unit, so they are not comparable with ours number for number.", "",
             "| claim (where the paper says it) | budget | pipeline | verdict | "
             + " | ".join(presets) + " | the paper's figures (its units) |",
             "|---|---|---|---|" + "---|" * len(presets) + "---|"]
    for c in claims:
        paper = _paper_text(c["paper"])
        lines.append(f"| **{c['statement']}** ({c['cite']}) | {_budget(c['eps'])} | "
                     f"{c['pipeline'] or '-'} | **{c['verdict']}** | "
                     + " | ".join(_cells(c, presets)) + f" | {paper} |")
        for s in c["secondary"]:
            lines.append(f"| secondary | {_budget(s['eps'])} | {s['pipeline'] or '-'} | "
                         f"{s['verdict']} | " + " | ".join(_cells(s, presets)) + " | - |")
    return "\n".join(lines) + "\n\n" + strength_markdown(document["ea_attack_strength"])


def strength_markdown(strength: list[dict]) -> str:
    """The efficiency attack's strength as a table: per preset, f clean and under EA at each
    budget (speed, slowdown with its t-interval, share of the possible slowdown, accuracy)."""
    lines = ["**How much the efficiency attack moves f** (the baseline of the EA claims): f's "
             "mean speed and accuracy clean and under EA at each budget; the slowdown is the "
             "mean per-frame clean minus EA speed with its 95% t-interval; 'of possible' is "
             "that slowdown over the largest a label flip can cause (every frame driven at f's "
             "slowest speed on any frame, the design of the preset's least grippy label).", "",
             "| preset | budget | speed (m/s) | slowdown (m/s) | of possible | accuracy |",
             "|---|---|---|---|---|---|"]
    for s in strength:
        lines.append(f"| {s['preset']} | clean | {s['clean_mps']:.2f} (slowest label "
                     f"{s['floor_mps']:.2f}) | - | - | {_pct(s['clean_accuracy'])} |")
        lines += [f"| {s['preset']} | EA eps = {e} | {v['slowdown_mps']['ea_mps']:.2f} | "
                  f"{_diff(v['slowdown_mps'])} | {v['of_possible']:.0%} | "
                  f"{_pct(v['accuracy'])} |" for e, v in s["ea_by_eps"].items()]
    return "\n".join(lines) + "\n"
