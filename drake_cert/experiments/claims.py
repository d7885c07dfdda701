"""The claims a reproduction checks on its per-frame rows (DESIGN 7.3).

``claims.md`` and ``claims.json`` (:func:`claims_document`) open with the headline of
:mod:`drake_cert.experiments.headline` (per pipeline, departures not conditioned on the truth,
with intervals that account for clustering by frame, beside f at the same budget) and its split
by whether the certified label range holds the true label, a diagnostic for every pipeline.
Then the paper's claims, one verdict each at its budget (:mod:`.paper_claims`), then, per
preset, over the frames the run holds (1-2 the paper's, 3-4 the project's own criteria):
1. the non-robust pipeline f is unstable under the safety attack (SA): the share of f's
   episodes that left the lane, per budget;
2. f loses speed under the efficiency attack (EA): mean velocity per budget against clean;
3. the certified pipeline g keeps 0% instability inside its certificates: among g's attacked
   episodes certified at the attack's budget (``certified``), how many left the lane, with a
   95% Clopper-Pearson upper bound, over all of them and over those whose frame g labels right
   when clean (the safe-set interval's standing assumption); departures listed frame by frame
   with g's clean label; the same episodes split by whether the certified label range (the
   labels of the design it selected) holds the frame's true label or misses it;
4. g keeps at least 80% of its clean speed under EA at the main budget, per sigma.

For g_conformal (the same certificates read by the robust conformal interval with the drive's
calibration) claim 3 is the guarantee that interval makes for one frame: its certified label
range misses the true label in at most the calibrations' own per-frame bound p
(:func:`conformal_miss_bounds`, DESIGN 3.6; 0.2518-0.2519 with the drive's settings), checked
as "the upper end of the misses' 95% Clopper-Pearson interval is within p". It does not promise 0%
instability for a single frame: the drive's promise comes from counting many looks (DESIGN 6.3),
which a one-frame episode does not have, so its departures are reported, not judged.

Shares carry their 95% two-sided Clopper-Pearson interval (claim 3's upper bound is its upper
end), counted over episodes as if independent; the headline's intervals are the ones that
account for departures clustering on frames (DESIGN 7.3).
"""

from __future__ import annotations

import numpy as np

from drake_cert.experiments import headline, paper_claims
from drake_cert.experiments.headline import holds_true_label

SPEED_KEPT = 0.8  # claim 4: the least share of g's clean speed kept under EA


_share = paper_claims.share


def _velocity(rows: list[dict]) -> float:
    return float(np.mean([r["velocity_mps"] for r in rows])) if rows else float("nan")




def _cell(mine: list[dict], pipeline: str, attack: str, eps=None, sigma=None) -> list[dict]:
    """The rows of one cell of a preset (eps and sigma: any, when None)."""
    return [r for r in mine if r["pipeline"] == pipeline and r["attack"] == attack
            and (eps is None or r["eps"] == eps) and (sigma is None or r["sigma"] == sigma)]


def _speed_kept(mine: list[dict], pipeline: str, main_eps: float) -> dict:
    """Per sigma of ``pipeline`` (ascending): clean and EA velocity at the main budget and
    their ratio."""
    kept = {}
    for s in sorted({r["sigma"] for r in mine if r["pipeline"] == pipeline}):
        clean, ea = _velocity(_cell(mine, pipeline, "none", main_eps, s)), _velocity(
            _cell(mine, pipeline, "ea", main_eps, s))
        kept[s] = dict(clean_mps=clean, ea_mps=ea, kept=ea / clean if clean > 0 else
                       float("nan"))
    return kept


def _f_claims(mine: list[dict]) -> tuple[float, dict, dict]:
    """Claims 1 and 2 of one preset: f's clean velocity, and per budget f's SA instability
    share and EA velocity."""
    budgets = sorted({r["eps"] for r in mine if r["pipeline"] == "f" and r["attack"] != "none"})
    f_clean = _velocity(_cell(mine, "f", "none"))
    f_sa = {e: _share(sum(r["left_lane"] for r in _cell(mine, "f", "sa", e)),
                      len(_cell(mine, "f", "sa", e)))
            for e in budgets}
    f_ea = {e: _velocity(_cell(mine, "f", "ea", e)) for e in budgets}
    return f_clean, f_sa, f_ea


def _g_certified(mine: list[dict], main_eps: float) -> tuple[list, list, list, list]:
    """Claim 3 of one preset: g's certified attacked episodes, those whose frame g labels right
    when clean, those whose certified range holds the true label, and the departures among
    them, frame by frame."""
    # g's label on the clean frame at each sigma (the main-budget clean cell where the
    # sweep's eps = 0 cell repeats it)
    clean_g = {(r["position"], r["sigma"]): r["predicted"]
               for r in sorted(_cell(mine, "g", "none"), key=lambda r: r["eps"] == main_eps)}
    certified = [r for r in mine if r["pipeline"] == "g" and r["attack"] != "none"
                 and r["certified"]]
    right = [r for r in certified
             if clean_g.get((r["position"], r["sigma"])) == r["true_label"]]
    holds_truth = [r for r in certified if holds_true_label(r)]
    departures = [dict(frame=r["frame"], true_label=r["true_label"], sigma=r["sigma"],
                       attack=r["attack"], eps=r["eps"], predicted=r["predicted"],
                       clean_prediction=clean_g.get((r["position"], r["sigma"])),
                       design=r["design_labels"], velocity_mps=r["velocity_mps"],
                       interval_covers=r["interval_covers"],
                       range_holds_true_label=holds_true_label(r))
                  for r in certified if r["left_lane"]]
    return certified, right, holds_truth, departures


def _conformal_claims(mine: list[dict], main_eps: float,
                      miss_bound: float | None) -> tuple[dict, dict]:
    """Claims 3 and 4 for g_conformal (the same certificates read by the robust conformal
    interval): the figures and the claims' verdicts, both empty without g_conformal rows.
    Claim 3 is judged against ``miss_bound`` (the calibration's per-frame miss bound p), and
    not at all without one."""
    conformal = [r for r in mine if r["pipeline"] == "g_conformal" and r["attack"] != "none"
                 and r["certified"]]
    conformal_kept = {str(s): v for s, v in _speed_kept(mine, "g_conformal", main_eps).items()}
    if not conformal_kept:
        return {}, {}
    misses = _share(sum(not holds_true_label(r) for r in conformal), len(conformal))
    figures = dict(
        g_conformal_inside_certificate=_share(sum(r["left_lane"] for r in conformal),
                                              len(conformal)),
        g_conformal_certified_range_misses_true_label=misses,
        g_conformal_miss_bound=miss_bound,
        g_conformal_ea_speed_kept=conformal_kept)
    holds = {}
    if miss_bound is not None:
        holds["g_conformal_misses_within_its_per_frame_bound"] = \
            misses["ci95_pct"][1] <= 100.0 * miss_bound
    holds["g_conformal_keeps_80pct_speed_under_ea"] = all(
        v["kept"] >= SPEED_KEPT for v in conformal_kept.values())
    return figures, holds


def check_claims(rows: list[dict], main_eps: float,
                 conformal_miss_bounds: dict[str, float] | None = None) -> dict:
    """Claims 1-4 for every preset in ``rows`` (frame rows of :mod:`reproduce`);
    ``conformal_miss_bounds``: per preset, g_conformal's per-frame miss bound p, which its
    claim 3 is judged against (:func:`conformal_miss_bounds`); a preset without one gets no
    claim-3 verdict."""
    bounds = conformal_miss_bounds or {}
    out = {}
    for preset in dict.fromkeys(r["preset"] for r in rows):
        mine = [r for r in rows if r["preset"] == preset]
        f_clean, f_sa, f_ea = _f_claims(mine)
        certified, right, holds_truth, departures = _g_certified(mine, main_eps)
        kept = _speed_kept(mine, "g", main_eps)
        with_conformal, conformal_holds = _conformal_claims(mine, main_eps, bounds.get(preset))
        out[preset] = dict(
            frames=len({r["position"] for r in mine}),
            f_clean_velocity_mps=f_clean,
            f_sa_instability={str(e): v for e, v in f_sa.items()},
            f_ea_velocity_mps={str(e): v for e, v in f_ea.items()},
            g_inside_certificate=_share(len(departures), len(certified)),
            g_inside_certificate_clean_right=_share(sum(r["left_lane"] for r in right),
                                                    len(right)),
            g_inside_certificate_range_holds=_share(
                sum(r["left_lane"] for r in holds_truth), len(holds_truth)),
            g_certified_range_misses_true_label=_share(len(certified) - len(holds_truth),
                                                       len(certified)),
            g_departures_inside_certificate=departures,
            g_ea_speed_kept={str(s): v for s, v in kept.items()},
            **with_conformal,
            holds=dict(
                f_unstable_under_sa=any(v["hits"] > 0 for v in f_sa.values()),
                f_slower_under_ea=any(v < f_clean for v in f_ea.values()),
                g_zero_instability_inside_certificates=not departures,
                g_zero_instability_inside_certificates_where_right_clean=not any(
                    r["left_lane"] for r in right),
                g_zero_instability_where_the_certified_range_holds_the_true_label=not any(
                    r["left_lane"] for r in holds_truth),
                g_keeps_80pct_speed_under_ea=all(v["kept"] >= SPEED_KEPT for v in kept.values()),
                # claims 3 and 4 for the same certificates read by the robust conformal interval
                **conformal_holds,
            ))
    return out


def markdown(claims: dict, main_eps: float) -> str:
    """The claims as Markdown: one table per claim, presets as columns."""
    presets = list(claims)
    head = "| | " + " | ".join(presets) + " |\n|---|" + "---|" * len(presets)

    def pct(s):
        return f"{s['hits']}/{s['total']} = {s['pct']:.1f}% [{s['ci95_pct'][0]:.1f}, " \
               f"{s['ci95_pct'][1]:.1f}]" if s["total"] else "n/a"

    def row(title, fn):
        return f"| {title} | " + " | ".join(fn(claims[p]) for p in presets) + " |"

    budgets = sorted({float(e) for c in claims.values() for e in c["f_sa_instability"]})
    sigmas = sorted({float(s) for c in claims.values() for s in c["g_ea_speed_kept"]})
    lines = ["Checked on the frames stated (episodes counted per frame and cell; shares with "
             "their 95% Clopper-Pearson interval).", "", head,
             row("frames per preset", lambda c: str(c["frames"])),
             "", "**1. f is unstable under SA** (episodes that left the lane)", "", head]
    lines += [row(f"eps = {e:g}", lambda c, e=e: pct(c["f_sa_instability"][str(e)]))
              for e in budgets]
    lines += ["", "**2. f loses speed under EA** (mean velocity, m/s)", "", head,
              row("clean", lambda c: f"{c['f_clean_velocity_mps']:.2f}")]
    lines += [row(f"EA eps = {e:g}", lambda c, e=e: f"{c['f_ea_velocity_mps'][str(e)]:.2f}")
              for e in budgets]
    lines += ["", "**3. g inside its certificates** (ours; attacked episodes whose run-time "
              "interval was certified at the attack's budget; departures / episodes)", "", head,
              row("left the lane", lambda c: pct(c["g_inside_certificate"])),
              row("... on frames g labels right when clean",
                  lambda c: pct(c["g_inside_certificate_clean_right"])),
              row("... where the certified label range holds the true label (a diagnostic: "
                  "f does not leave its lane there either, see above)",
                  lambda c: pct(c["g_inside_certificate_range_holds"])),
              row("certified label range misses the true label",
                  lambda c: pct(c["g_certified_range_misses_true_label"]))]
    conformal = all("g_conformal_inside_certificate" in c for c in claims.values())
    if conformal:  # the same certificates, read by the robust conformal interval
        lines += [row("g_conformal (robust conformal interval): left the lane",
                      lambda c: pct(c["g_conformal_inside_certificate"])),
                  row("g_conformal: certified label range misses the true label (its "
                      "guarantee: at most the calibration's per-frame bound p)",
                      lambda c: pct(c["g_conformal_certified_range_misses_true_label"])
                      + (f" (p = {100 * c['g_conformal_miss_bound']:.2f}%)"
                         if c.get("g_conformal_miss_bound") is not None else ""))]
    lines += ["", f"**4. g's speed under EA at eps = {main_eps:g}, share of its clean speed** "
              f"(our criterion: >= {SPEED_KEPT:.0%})", "", head]
    lines += [row(f"sigma = {s:g}", lambda c, s=s: "{:.2f} / {:.2f} m/s = {:.0%}".format(
        c["g_ea_speed_kept"][str(s)]["ea_mps"], c["g_ea_speed_kept"][str(s)]["clean_mps"],
        c["g_ea_speed_kept"][str(s)]["kept"])) for s in sigmas]
    if conformal:
        lines += [row(f"sigma = {s:g}, g_conformal", lambda c, s=s: "{:.2f} / {:.2f} m/s = {:.0%}"
                      .format(*(c["g_conformal_ea_speed_kept"][str(s)][k]
                                for k in ("ea_mps", "clean_mps", "kept"))))
                  for s in sigmas]
    lines += ["", "**Holds?**", "", head]
    for key in next(iter(claims.values()))["holds"]:
        whose = " (the paper's)" if key.startswith("f_") else " (ours)"
        lines.append(row(key.replace("_", " ") + whose,
                         lambda c, k=key: "yes" if c["holds"][k] else "NO"))
    deps = [(p, d) for p in presets for d in claims[p]["g_departures_inside_certificate"]]
    if deps:
        lines += ["", "Departures of g inside its certificates (each a frame and cell):", "",
                  "| preset | frame | true label | sigma | attack | eps | g's label (clean) | "
                  "g's label (attacked) | design | interval holds the true stiffness | "
                  "range holds the true label |",
                  "|---|---|---|---|---|---|---|---|---|---|---|"]
        lines += [f"| {p} | {d['frame']} | {d['true_label']} | {d['sigma']:g} | {d['attack']} | "
                  f"{d['eps']:g} | {d['clean_prediction']} | {d['predicted']} | {d['design']} | "
                  f"{d['interval_covers']} | {d['range_holds_true_label']} |" for p, d in deps]
        lines += ["", "A certified label range holds on the whole eps-ball, the clean frame "
                  "included: where g's clean label is already wrong, the certificate carries "
                  "that error (the safe-set interval's standing assumption; the robust "
                  "conformal interval, pipeline g_conformal, does not rest on it)."]
    return "\n".join(lines) + "\n"


def conformal_miss_bounds(calibrations: dict) -> dict[str, float]:
    """Per preset, the per-frame miss bound p that its g_conformal calibrations promise: the
    largest ``alpha_total`` (its largest bin bound alpha_c plus the smoothing bounds' levels
    beta_cal and beta_test, DESIGN 3.6) over its sigmas, since claim 3 pools the sigmas.
    ``calibrations``: ``{(preset, sigma): RobustConformalCalibration}``, as the run store keeps
    them."""
    out: dict[str, float] = {}
    for (preset, _sigma), calibration in calibrations.items():
        out[preset] = max(out.get(preset, 0.0), float(calibration.alpha_total))
    return out


def claims_document(rows: list[dict], main_eps: float, *, resamples: int = headline.RESAMPLES,
                    seed: int = headline.SEED,
                    conformal_miss_bounds: dict[str, float] | None = None) -> dict:
    """What ``claims.json`` holds, in this order: ``headline`` (:func:`headline.headline`),
    ``truth_conditioned_diagnostic`` (:func:`headline.truth_conditioned`), ``paper_claims``
    (one verdict per claim of the paper at its budget, :func:`paper_claims.paper_claims`), then
    the figures 1-4 per preset (:func:`check_claims`, one key per preset)."""
    return dict(headline=headline.headline(rows, resamples=resamples, seed=seed),
                truth_conditioned_diagnostic=headline.truth_conditioned(rows),
                paper_claims=paper_claims.paper_claims(rows),
                **check_claims(rows, main_eps, conformal_miss_bounds))


def preset_claims(document: dict) -> dict:
    """The per-preset part of a :func:`claims_document` (or of a ``claims.json`` read back)."""
    return {k: v for k, v in document.items()
            if k not in ("headline", "truth_conditioned_diagnostic", "paper_claims")}


def document_markdown(document: dict, main_eps: float, interval: str = "safe_set") -> str:
    """``claims.md``: the headline and its diagnostic first, then the paper's claims with one
    verdict each at the paper's budget (secondary rows under it), then the figures per preset
    (the paper's claims about f, and the project's own criteria for g); ``interval``: the
    run's interval for ``g`` (names it in the headline)."""
    text = headline.markdown(document["headline"], document["truth_conditioned_diagnostic"],
                             main_eps=main_eps, names=headline.display_names(interval))
    if document.get("paper_claims"):
        text += ("\n**The paper's claims, one verdict each at the paper's budget** "
                 "(`paper_claims` in claims.json)\n\n"
                 + paper_claims.markdown(document["paper_claims"]))
    return (text + "\n**Figures per preset: f under attack (the paper's claims 1-2) and the "
            "project's own criteria for g (3-4, docs/design.md 7.3; not the paper's)**\n\n"
            + markdown(preset_claims(document), main_eps))
