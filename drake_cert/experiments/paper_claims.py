"""The paper's own claims, each tested per data set and budget on a reproduction's frame rows.

:func:`paper_claims` returns the list ``claims.json`` stores under ``paper_claims``: one entry
per claim, preset, budget (and, for claims about g, per pipeline reading g's certificates),
``{claim, statement, preset, budget, pipeline, holds, significant, figures, rule, paper}``.
``holds`` is the claim's direction on the point estimates (None where the run has no rows to
test it at that budget, with ``figures["why"]``); ``significant`` says whether the 95%
Clopper-Pearson intervals of the two shares compared do not overlap (None for speeds and
errors, which are compared as measured). ``paper`` is the paper's figure behind the claim,
given only at the budget that reads its delta = 255 (eps = 1, docs/design.md 7.1).

The project's own criteria (zero instability inside certificates, 80% of the clean speed kept)
are not here: :mod:`drake_cert.experiments.claims` checks them and labels them as ours.
"""

from __future__ import annotations

import math

import numpy as np

from drake_cert.experiments.perception_eval import clopper_pearson_interval
from drake_cert.experiments.reproduce_config import PAPER_BUDGET_EPS

BUDGETS = (0.25, PAPER_BUDGET_EPS)  # the main budget and the paper's delta = 255 read as eps
G_PIPELINES = ("g", "g_conformal")

# The paper's best sigma against the safety attack (its ablation, Section V).
PAPER_BEST_SIGMA = {"carla-like": 0.25, "rtk-like": 0.25, "robotcar-like": 0.5}

# What the paper states, in our words, with where it says so.
STATEMENTS = {
    "f_accuracy_drops_under_attack":
        "f's accuracy drops under attack (Table VI: 0 / 80 / 69% at delta = 255)",
    "f_unstable_under_sa": "f leaves its lane more under SA than clean (Table VI)",
    "f_slower_under_ea": "f drives slower under EA than clean (Table VI)",
    "g_less_unstable_than_f_under_sa":
        "g leaves its lane less than f under SA (Tables VI, VIII; Section V)",
    "g_at_least_as_fast_as_f_under_ea":
        "g drives at least as fast as f under EA (Tables VI, IX: 'efficiency increased')",
    "sigma_ablation_best_sigma":
        "the best sigma against SA is 0.25 (carla), 0.25 (rtk), 0.5 (robotcar) (Section V)",
    "f_reg_stable_clean": "f_reg never leaves its lane without attack (Table VIII: 0.0)",
    "f_reg_unstable_under_sa": "f_reg leaves its lane under SA (Table IX: 200)",
    "f_reg_error_grows_under_attack": "f_reg's squared error grows under attack (Tables VIII-IX)",
    "h_stable_under_sa": "h never leaves its lane under SA (Table XI: 0.0 at every sigma)",
    "h_at_least_as_fast_as_f_reg_under_ea":
        "h drives at least as fast as f_reg under EA (Section V: 'stability and efficiency')",
}

# The paper's figure behind a claim per preset (carla, rtk, robotcar), at delta = 255.
_PAPER_FIGURES = {
    "f_accuracy_drops_under_attack": ("98.6 -> 0%", "94.2 -> 80%", "95.6 -> 69%"),
    "f_unstable_under_sa": ("0 -> 200 (its instability)", "0 -> 37.5", "0 -> 61.5"),
    "f_slower_under_ea": ("29.42 -> 27.36 m/s", "28.45 -> 27.83 m/s", "28.46 -> 25.35 m/s"),
    "g_less_unstable_than_f_under_sa": ("200 -> 6.36-25.0", "37.5 -> 18.99-29.30",
                                        "61.5 -> 6.82-23.29"),
    "g_at_least_as_fast_as_f_under_ea": ("27.36 -> 29.41-29.42 m/s", "27.83 -> 28.10-28.22 m/s",
                                         "25.35 -> 27.64-28.12 m/s"),
    "sigma_ablation_best_sigma": ("0.25", "0.25", "0.5"),
    "f_reg_stable_clean": ("0.0", "0.0", "0.0"),
    "f_reg_unstable_under_sa": ("200", "200", "200"),
    "f_reg_error_grows_under_attack": ("MSE 0.008 -> 0.44", "0.017 -> 0.43", "0.016 -> 0.45"),
    "h_stable_under_sa": ("0.0", "0.0", "0.0"),
    "h_at_least_as_fast_as_f_reg_under_ea": ("15.04-16.32 vs h 15.83-16.79 m/s (attack on h "
                                             "not stated)",) * 3,
}
_PRESET_ORDER = ("carla-like", "rtk-like", "robotcar-like")


def share(hits: int, total: int) -> dict:
    """``hits`` of ``total`` as a share in % with its two-sided 95% Clopper-Pearson interval."""
    if total == 0:
        return dict(hits=0, total=0, pct=math.nan, ci95_pct=[0.0, 100.0])
    lo, hi = clopper_pearson_interval(hits, total)
    return dict(hits=hits, total=total, pct=100.0 * hits / total,
                ci95_pct=[100.0 * lo, 100.0 * hi])


def _separated(a: dict, b: dict) -> bool:
    """Whether the 95% intervals of two shares do not overlap (either way round)."""
    return a["total"] > 0 and b["total"] > 0 and (
        a["ci95_pct"][1] < b["ci95_pct"][0] or b["ci95_pct"][1] < a["ci95_pct"][0])


def _rows(mine: list[dict], pipeline: str, attack: str, eps=None, sigma=None) -> list[dict]:
    """One cell's rows (a clean cell: any budget, the first one the run holds)."""
    cell = [r for r in mine if r["pipeline"] == pipeline and r["attack"] == attack
            and (sigma is None or r["sigma"] == sigma)]
    if attack == "none":
        first = min((r["eps"] for r in cell), default=None)
        return [r for r in cell if r["eps"] == first]
    return [r for r in cell if r["eps"] == eps]


def _left(rows: list[dict]) -> dict:
    return share(sum(bool(r["left_lane"]) for r in rows), len(rows))


def _right(rows: list[dict]) -> dict:
    return share(sum(r["predicted"] == r["true_label"] for r in rows), len(rows))


def _speed(rows: list[dict]) -> float:
    return float(np.mean([r["velocity_mps"] for r in rows])) if rows else math.nan


def _sq_error_kn2(rows: list[dict]) -> float:
    return float(np.mean([((float(r["predicted"]) - r["stiffness_n_per_rad"]) / 1e3) ** 2
                          for r in rows])) if rows else math.nan


def _missing(what: str) -> tuple[None, None, dict]:
    return None, None, {"why": f"the run has no {what} at this budget"}


def _sigmas(mine: list[dict], pipeline: str, attack: str, eps: float) -> list[float]:
    return sorted({r["sigma"] for r in mine if r["pipeline"] == pipeline
                   and r["attack"] == attack and r["eps"] == eps})


def f_accuracy_drops(mine, eps, _pipe):
    clean = _right(_rows(mine, "f", "none"))
    attacked = {a: _right(_rows(mine, "f", a, eps)) for a in ("sa", "ea")}
    if not clean["total"] or not all(s["total"] for s in attacked.values()):
        return _missing("f rows clean and under both attacks")
    holds = all(s["pct"] < clean["pct"] for s in attacked.values())
    sig = all(_separated(s, clean) for s in attacked.values())
    return holds, sig, dict(clean_accuracy=clean, sa_accuracy=attacked["sa"],
                            ea_accuracy=attacked["ea"])


def f_unstable_under_sa(mine, eps, _pipe, pipeline="f"):
    clean, sa = _left(_rows(mine, pipeline, "none")), _left(_rows(mine, pipeline, "sa", eps))
    if not clean["total"] or not sa["total"]:
        return _missing(f"{pipeline} rows clean and under SA")
    return sa["pct"] > clean["pct"], _separated(clean, sa), dict(clean_left_lane=clean,
                                                                 sa_left_lane=sa)


def f_slower_under_ea(mine, eps, _pipe):
    clean, ea = _speed(_rows(mine, "f", "none")), _speed(_rows(mine, "f", "ea", eps))
    if math.isnan(clean) or math.isnan(ea):
        return _missing("f rows clean and under EA")
    return ea < clean, None, dict(clean_mps=clean, ea_mps=ea)


def g_less_unstable(mine, eps, pipe):
    f_sa = _left(_rows(mine, "f", "sa", eps))
    sigmas = _sigmas(mine, pipe, "sa", eps)
    if not f_sa["total"] or not sigmas:
        return _missing(f"f and {pipe} rows under SA")
    per = {s: _left(_rows(mine, pipe, "sa", eps, s)) for s in sigmas}
    ok = {s: g["pct"] < f_sa["pct"] or g["pct"] == f_sa["pct"] == 0 for s, g in per.items()}
    sig = all(_separated(g, f_sa) for g in per.values())
    return all(ok.values()), sig, dict(f_sa_left_lane=f_sa, sa_left_lane_by_sigma={
        f"{s:g}": dict(g, holds=ok[s]) for s, g in per.items()})


def g_at_least_as_fast(mine, eps, pipe):
    f_ea = _speed(_rows(mine, "f", "ea", eps))
    sigmas = _sigmas(mine, pipe, "ea", eps)
    if math.isnan(f_ea) or not sigmas:
        return _missing(f"f and {pipe} rows under EA")
    per = {s: _speed(_rows(mine, pipe, "ea", eps, s)) for s in sigmas}
    return all(v >= f_ea for v in per.values()), None, dict(
        f_ea_mps=f_ea, ea_mps_by_sigma={f"{s:g}": v for s, v in per.items()})


def best_sigma(mine, eps, pipe):
    sigmas = _sigmas(mine, pipe, "sa", eps)
    if len(sigmas) < 2:
        return _missing(f"{pipe} at two or more sigmas under SA")
    preset = mine[0]["preset"]
    per = {s: _left(_rows(mine, pipe, "sa", eps, s)) for s in sigmas}
    low = min(v["pct"] for v in per.values())
    best = [s for s, v in per.items() if v["pct"] == low]
    paper = PAPER_BEST_SIGMA.get(preset)
    if paper is None or paper not in per:
        return _missing(f"{pipe} at the paper's best sigma")
    others = [v for s, v in per.items() if s != paper]
    sig = len(best) == 1 and all(_separated(per[paper], v) for v in others)
    return paper in best, sig, dict(paper_best_sigma=paper, best_sigmas=best,
                                    sa_left_lane_by_sigma={f"{s:g}": v for s, v in per.items()})


def f_reg_stable_clean(mine, _eps, _pipe):
    clean = _left(_rows(mine, "f_reg", "none"))
    if not clean["total"]:
        return _missing("f_reg clean rows")
    return clean["hits"] == 0, None, dict(clean_left_lane=clean)


def f_reg_unstable_under_sa(mine, eps, pipe):
    return f_unstable_under_sa(mine, eps, pipe, pipeline="f_reg")


def f_reg_error_grows(mine, eps, _pipe):
    clean = _sq_error_kn2(_rows(mine, "f_reg", "none"))
    attacked = {a: _sq_error_kn2(_rows(mine, "f_reg", a, eps)) for a in ("sa", "ea")}
    if math.isnan(clean) or any(math.isnan(v) for v in attacked.values()):
        return _missing("f_reg rows clean and under both attacks")
    return all(v > clean for v in attacked.values()), None, dict(
        clean_sq_error_kn2=clean, sa_sq_error_kn2=attacked["sa"], ea_sq_error_kn2=attacked["ea"])


def h_stable_under_sa(mine, eps, _pipe):
    sigmas = _sigmas(mine, "h", "sa", eps)
    if not sigmas:
        return _missing("h rows under SA")
    per = {s: _left(_rows(mine, "h", "sa", eps, s)) for s in sigmas}
    certified = {s: sum(bool(r["certified"]) for r in _rows(mine, "h", "sa", eps, s))
                 for s in sigmas}
    return all(v["hits"] == 0 for v in per.values()), None, dict(
        sa_left_lane_by_sigma={f"{s:g}": dict(v, certified=certified[s]) for s, v in per.items()})


def h_as_fast_as_f_reg(mine, eps, _pipe):
    f_ea = _speed(_rows(mine, "f_reg", "ea", eps))
    sigmas = _sigmas(mine, "h", "ea", eps)
    if math.isnan(f_ea) or not sigmas:
        return _missing("f_reg and h rows under EA")
    per = {s: _speed(_rows(mine, "h", "ea", eps, s)) for s in sigmas}
    return all(v >= f_ea for v in per.values()), None, dict(
        f_reg_ea_mps=f_ea, ea_mps_by_sigma={f"{s:g}": v for s, v in per.items()})


# claim -> (test, rule, whether it is tested per g pipeline, whether it has a budget)
CLAIMS = {
    "f_accuracy_drops_under_attack": (
        f_accuracy_drops, "f's accuracy under SA and under EA each below its clean accuracy",
        False, True),
    "f_unstable_under_sa": (f_unstable_under_sa, "share of f's SA episodes that left the lane "
                            "above the clean share", False, True),
    "f_slower_under_ea": (f_slower_under_ea, "f's mean EA speed below its clean speed", False,
                          True),
    "g_less_unstable_than_f_under_sa": (
        g_less_unstable, "at every sigma, the share of g's SA episodes (all of them: an "
        "abstention drives the envelope) that left the lane below f's (or both 0)", True, True),
    "g_at_least_as_fast_as_f_under_ea": (
        g_at_least_as_fast, "at every sigma, g's mean EA speed >= f's", True, True),
    "sigma_ablation_best_sigma": (
        best_sigma, "the paper's best sigma among those with the fewest SA departures of g",
        True, True),
    "f_reg_stable_clean": (f_reg_stable_clean, "no clean f_reg episode left the lane", False,
                           False),
    "f_reg_unstable_under_sa": (f_reg_unstable_under_sa, "share of f_reg's SA episodes that "
                                "left the lane above the clean share", False, True),
    "f_reg_error_grows_under_attack": (
        f_reg_error_grows, "f_reg's mean squared stiffness error under SA and under EA each "
        "above the clean one", False, True),
    "h_stable_under_sa": (h_stable_under_sa, "no SA episode of h left the lane, at every sigma",
                          False, True),
    "h_at_least_as_fast_as_f_reg_under_ea": (
        h_as_fast_as_f_reg, "at every sigma, h's mean EA speed >= f_reg's", False, True),
}


def _paper_figure(claim: str, preset: str, budget) -> str | None:
    figures = _PAPER_FIGURES.get(claim)
    if figures is None or preset not in _PRESET_ORDER:
        return None
    if budget is not None and budget != PAPER_BUDGET_EPS:
        return None
    return figures[_PRESET_ORDER.index(preset)]


def paper_claims(rows: list[dict], budgets=BUDGETS) -> list[dict]:
    """Every claim of :data:`CLAIMS` per preset in ``rows`` and budget (module docstring)."""
    out = []
    presets = list(dict.fromkeys(r["preset"] for r in rows))
    held = {r["pipeline"] for r in rows}
    for claim, (test, rule, per_g, has_budget) in CLAIMS.items():
        pipes = [p for p in G_PIPELINES if p in held] if per_g else [None]
        for preset in presets:
            mine = [r for r in rows if r["preset"] == preset]
            for budget in (budgets if has_budget else (None,)):
                for pipe in pipes:
                    holds, significant, figures = test(mine, budget, pipe)
                    out.append(dict(claim=claim, statement=STATEMENTS[claim], preset=preset,
                                    budget=budget, pipeline=pipe, holds=holds,
                                    significant=significant, figures=figures, rule=rule,
                                    paper=_paper_figure(claim, preset, budget)))
    return out


def _verdict(entry: dict) -> str:
    if entry["holds"] is None:
        return "not tested"
    word = "holds" if entry["holds"] else "FAILS"
    if entry["significant"] is not None:
        word += " (95% intervals apart)" if entry["significant"] else " (intervals overlap)"
    return word


def _pct(share: dict) -> str:
    return f"{share['hits']}/{share['total']}" if share["total"] else "n/a"


def _by_sigma(values: dict, fmt) -> str:
    return " / ".join(fmt(v) for v in values.values()) + \
        f" (sigma {' / '.join(values)})"


def brief(entry: dict) -> str:
    """The figures behind one verdict, in a few words."""
    f, claim = entry["figures"], entry["claim"]
    if claim == "f_accuracy_drops_under_attack":
        return (f"right clean {_pct(f['clean_accuracy'])}, SA {_pct(f['sa_accuracy'])}, "
                f"EA {_pct(f['ea_accuracy'])}")
    if claim in ("f_unstable_under_sa", "f_reg_unstable_under_sa"):
        return f"left clean {_pct(f['clean_left_lane'])}, SA {_pct(f['sa_left_lane'])}"
    if claim == "f_slower_under_ea":
        return f"{f['clean_mps']:.2f} -> {f['ea_mps']:.2f} m/s"
    if claim == "g_less_unstable_than_f_under_sa":
        return (f"left f {_pct(f['f_sa_left_lane'])}, g "
                + _by_sigma(f["sa_left_lane_by_sigma"], _pct))
    if claim == "g_at_least_as_fast_as_f_under_ea":
        return (f"f {f['f_ea_mps']:.2f}, g "
                + _by_sigma(f["ea_mps_by_sigma"], lambda v: f"{v:.2f}") + " m/s")
    if claim == "sigma_ablation_best_sigma":
        return (f"fewest at sigma {' / '.join(f'{s:g}' for s in f['best_sigmas'])}; left "
                + _by_sigma(f["sa_left_lane_by_sigma"], _pct))
    if claim == "f_reg_stable_clean":
        return f"left {_pct(f['clean_left_lane'])}"
    if claim == "f_reg_error_grows_under_attack":
        return (f"{f['clean_sq_error_kn2']:.0f} -> SA {f['sa_sq_error_kn2']:.0f}, EA "
                f"{f['ea_sq_error_kn2']:.0f} (kN/rad)^2")
    if claim == "h_stable_under_sa":
        return "left " + _by_sigma(f["sa_left_lane_by_sigma"],
                                   lambda v: f"{_pct(v)} ({v['certified']} certified)")
    if claim == "h_at_least_as_fast_as_f_reg_under_ea":
        return (f"f_reg {f['f_reg_ea_mps']:.2f}, h "
                + _by_sigma(f["ea_mps_by_sigma"], lambda v: f"{v:.2f}") + " m/s")
    return ""


def label(entry: dict) -> str:
    """``claim preset eps [pipeline]``: one entry's name in a line."""
    budget = "clean" if entry["budget"] is None else f"eps {entry['budget']:g}"
    return " ".join(x for x in (entry["claim"], entry["preset"], budget, entry["pipeline"]) if x)


def verdict_counts(claims: list[dict]) -> dict:
    """How many entries hold, fail and were not tested."""
    return dict(holds=sum(c["holds"] is True for c in claims),
                fails=sum(c["holds"] is False for c in claims),
                not_tested=sum(c["holds"] is None for c in claims))


def markdown(claims: list[dict]) -> str:
    """One table: a row per claim (and budget, g pipeline), a verdict per preset."""
    presets = list(dict.fromkeys(c["preset"] for c in claims))
    keys = list(dict.fromkeys((c["claim"], c["budget"], c["pipeline"]) for c in claims))
    by = {(c["claim"], c["budget"], c["pipeline"], c["preset"]): c for c in claims}
    counts = verdict_counts(claims)
    lines = [f"{counts['holds']} hold, {counts['fails']} FAIL, {counts['not_tested']} not "
             "tested (the run holds no rows for them). A verdict is the claim's direction on "
             "the point estimates; where two shares are compared, whether their 95% "
             "Clopper-Pearson intervals are apart is said beside it. The paper's figure "
             f"stands only in the eps = {PAPER_BUDGET_EPS:g} rows (its delta = 255) and the "
             "clean ones.", "",
             "| claim | budget | pipeline | " + " | ".join(presets) + " | rule |",
             "|---|---|---|" + "---|" * len(presets) + "---|"]
    for claim, budget, pipe in keys:
        cells = []
        for p in presets:
            e = by.get((claim, budget, pipe, p))
            cell = _verdict(e) if e else "n/a"
            if e and e["holds"] is not None:
                cell += f": {brief(e)}"
            if e and e["paper"]:
                cell += f"; paper: {e['paper']}"
            cells.append(cell)
        text = STATEMENTS[claim]
        lines.append(f"| {text} | {'clean' if budget is None else f'eps = {budget:g}'} | "
                     f"{pipe or '-'} | " + " | ".join(cells) + f" | {CLAIMS[claim][1]} |")
    return "\n".join(lines) + "\n"


def failing(claims: list[dict]) -> list[str]:
    """One line per claim that fails somewhere: its statement and where it fails (preset,
    budget, g's interval), in the order of ``claims``; the README's summary quotes these."""
    where: dict[str, list[str]] = {}
    tested: dict[str, int] = {}
    for c in claims:
        if c["holds"] is not None:
            tested[c["claim"]] = tested.get(c["claim"], 0) + 1
        if c["holds"] is False:
            budget = "clean" if c["budget"] is None else f"eps {c['budget']:g}"
            pipe = f" ({c['pipeline']})" if c["pipeline"] else ""
            where.setdefault(c["claim"], []).append(f"{c['preset']} {budget}{pipe}")
    return [f"{STATEMENTS[claim]}: fails on every preset, budget and interval tested "
            f"({len(places)} of {tested[claim]})" if len(places) == tested[claim] > 1
            else f"{STATEMENTS[claim]}: fails on {', '.join(places)}"
            for claim, places in where.items()]
