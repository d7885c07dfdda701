"""The paper's claims checked on per-frame rows: each claim flips when the rows contradict it."""

from drake_cert.experiments.claims import (
    check_claims,
    claims_document,
    document_markdown,
    markdown,
    preset_claims,
)


def row(pipeline, attack, eps, *, sigma=0.0, left=False, v=10.0, certified=False, position=0):
    return dict(preset="p", position=position, frame=position, true_label="dry",
                pipeline=pipeline, sigma=sigma, attack=attack, eps=eps, left_lane=left,
                velocity_mps=v, certified=certified, predicted="dry", design_labels="dry",
                interval_covers=True)


def frame(position, *, f_left=True, g_left=False, g_ea_v=9.0):
    return [row("f", "none", 0.25, v=10.0, position=position),
            row("f", "sa", 0.25, left=f_left, position=position),
            row("f", "ea", 0.25, v=7.0, position=position),
            row("g", "none", 0.25, sigma=0.5, v=10.0, certified=True, position=position),
            row("g", "sa", 0.25, sigma=0.5, left=g_left, certified=True, position=position),
            row("g", "ea", 0.25, sigma=0.5, v=g_ea_v, certified=True, position=position)]


def test_the_claims_hold_when_f_fails_and_g_holds():
    c = check_claims(frame(0) + frame(1, f_left=False), 0.25)["p"]
    assert c["frames"] == 2
    assert c["f_sa_instability"]["0.25"]["hits"] == 1
    assert c["f_sa_instability"]["0.25"]["pct"] == 50.0
    assert c["f_ea_velocity_mps"]["0.25"] == 7.0 < c["f_clean_velocity_mps"]
    assert c["g_inside_certificate"]["total"] == 4  # g's attacked certified episodes
    assert c["g_ea_speed_kept"]["0.5"]["kept"] == 0.9
    assert all(c["holds"].values())
    assert "yes" in markdown({"p": c}, 0.25)


def test_a_departure_inside_a_certificate_and_a_slow_g_break_the_claims():
    c = check_claims(frame(0, g_left=True, g_ea_v=6.0) + frame(1), 0.25)["p"]
    assert c["holds"]["g_zero_instability_inside_certificates"] is False
    assert c["holds"]["g_keeps_80pct_speed_under_ea"] is False  # 7.5 / 10.0 m/s
    assert c["g_inside_certificate"]["hits"] == 1
    assert c["g_inside_certificate"]["ci95_pct"][1] > 50.0  # 1 of 4: a wide interval
    assert len(c["g_departures_inside_certificate"]) == 1
    # g labels frame 0 right when clean ("dry"): the departure counts in the conditioned share too
    assert c["g_inside_certificate_clean_right"]["hits"] == 1
    text = markdown({"p": c}, 0.25)
    assert "NO" in text and "Departures of g" in text


def test_a_departure_on_a_frame_g_labels_wrong_when_clean_is_told_apart():
    rows = frame(0, g_left=True) + frame(1)
    for r in rows:
        if r["position"] == 0 and r["pipeline"] == "g" and r["attack"] == "none":
            r["predicted"] = "wet"
    c = check_claims(rows, 0.25)["p"]
    assert c["holds"]["g_zero_instability_inside_certificates"] is False
    assert c["holds"]["g_zero_instability_inside_certificates_where_right_clean"] is True
    assert c["g_inside_certificate_clean_right"]["total"] == 2  # frame 1's SA and EA
    assert c["g_departures_inside_certificate"][0]["clean_prediction"] == "wet"


def test_departures_are_split_by_whether_the_certified_range_holds_the_true_label():
    """A departure under a design whose label range excludes the true label is the perception
    claim failing; one under a range that holds it would be the controller's."""
    rows = frame(0, g_left=True) + frame(1)
    for r in rows:
        if r["position"] == 0 and r["pipeline"] == "g" and r["attack"] == "sa":
            r["design_labels"] = "grippy+dry2"  # the certified range misses "dry"
    c = check_claims(rows, 0.25)["p"]
    assert c["g_certified_range_misses_true_label"]["hits"] == 1
    assert c["g_inside_certificate_range_holds"] == dict(c["g_inside_certificate_range_holds"],
                                                         hits=0, total=3)
    assert c["holds"]["g_zero_instability_where_the_certified_range_holds_the_true_label"]
    assert not c["g_departures_inside_certificate"][0]["range_holds_true_label"]
    rows[4]["design_labels"] = "dry+wet"  # now the range holds the true label: the claim breaks
    c = check_claims(rows, 0.25)["p"]
    assert not c["holds"]["g_zero_instability_where_the_certified_range_holds_the_true_label"]
    assert "range holds the true label" in markdown({"p": c}, 0.25)


def test_claims_lead_with_the_unconditioned_headline_and_keep_the_split_as_a_diagnostic():
    """claims.json and claims.md open with the departures not conditioned on the truth (f
    beside g); the split by the true label follows, for f as for g, then claims 1-4."""
    rows = frame(0, g_left=True) + frame(1, f_left=False)
    for r in rows:
        if r["position"] == 0 and r["attack"] == "sa":
            r["design_labels"] = "grippy"  # g's and f's ranges miss "dry" on frame 0
    doc = claims_document(rows, 0.25, resamples=200)
    assert list(doc)[:4] == ["headline", "truth_conditioned_diagnostic", "paper_claims", "p"]
    assert preset_claims(doc) == {"p": check_claims(rows, 0.25)["p"]}
    g = next(r for r in doc["headline"]["rows"] if r["pipeline"] == "g"
             and r["selection"] == "all" and r["preset"] == "all")
    assert (g["departures"], g["episodes"]) == (1, 4)
    split = doc["truth_conditioned_diagnostic"]
    assert split["g"]["holds"]["departures"] == split["f"]["holds"]["departures"] == 0
    assert split["f"]["misses"] == dict(departures=1, episodes=1)  # frame 0's f under SA
    text = document_markdown(doc, 0.25, "conformal")
    assert text.startswith("**Left the lane, not conditioned on the truth**")
    assert text.index("Diagnostic: split") < text.index("**1. f is unstable under SA**")
    assert "g (robust conformal interval)" in text  # the run's interval names g


def with_conformal(rows, *, left=False, ea_v=9.0):
    """g's rows again as g_conformal (the same certificates, the robust conformal interval)."""
    out = []
    for r in rows:
        if r["pipeline"] == "g":
            c = dict(r, pipeline="g_conformal")
            if r["attack"] == "sa":
                c["left_lane"] = left
            if r["attack"] == "ea":
                c["velocity_mps"] = ea_v
            out.append(c)
    return rows + out


def test_claims_three_and_four_are_checked_for_the_conformal_interval_too():
    """g_conformal's claim 3 is its per-frame guarantee: its certified ranges miss the true
    label in at most p of the episodes (the misses' 95% upper end within p); a departure alone
    does not break it, since one frame has no counting of looks."""
    rows = [r for k in range(40) for r in frame(k, f_left=k == 0)]
    holds = check_claims(with_conformal(rows), 0.25, {"p": 0.25})["p"]["holds"]
    assert holds["g_conformal_misses_within_its_per_frame_bound"] is True
    assert holds["g_conformal_keeps_80pct_speed_under_ea"] is True
    departing = check_claims(with_conformal(rows, left=True), 0.25, {"p": 0.25})["p"]
    assert departing["holds"]["g_conformal_misses_within_its_per_frame_bound"] is True
    assert departing["g_conformal_inside_certificate"]["hits"] == 40  # reported, not judged
    missing = with_conformal(rows, ea_v=6.0)
    for r in missing:  # 10 of the 80 attacked certified episodes: the range misses "dry"
        if r["pipeline"] == "g_conformal" and r["attack"] == "sa" and r["position"] < 10:
            r["design_labels"] = "wet"
    broken = check_claims(missing, 0.25, {"p": 0.25})["p"]
    assert broken["g_conformal_certified_range_misses_true_label"]["hits"] == 10
    assert broken["g_conformal_certified_range_misses_true_label"]["ci95_pct"][1] < 25.0
    assert broken["holds"]["g_conformal_misses_within_its_per_frame_bound"] is True
    tight = check_claims(missing, 0.25, {"p": 0.1})["p"]["holds"]  # 12.5% observed against p = 10%
    assert tight["g_conformal_misses_within_its_per_frame_bound"] is False
    assert broken["holds"]["g_conformal_keeps_80pct_speed_under_ea"] is False
    assert broken["holds"]["g_zero_instability_inside_certificates"] is True  # g unchanged
    assert "g_conformal_misses_within_its_per_frame_bound" not in check_claims(
        with_conformal(rows), 0.25)["p"]["holds"]  # without a bound there is no such verdict
    assert "g_conformal_misses_within_its_per_frame_bound" not in check_claims(
        with_conformal(rows), 0.25, {"q": 0.25})["p"]["holds"]  # nor with another preset's
    assert "g_conformal_misses_within_its_per_frame_bound" not in check_claims(
        rows, 0.25, {"p": 0.25})["p"]["holds"]  # a run without the pipeline has no such verdict
    assert "(p = 25.00%)" in markdown({"p": broken}, 0.25)


def test_each_presets_miss_bound_is_the_largest_bound_its_calibrations_promise():
    """Claim 3 pools a preset's sigmas, so its p is the largest alpha_c + beta_cal + beta_test
    of that preset's calibrations, each calibration's own (not the run's target)."""
    from drake_cert.certification.conformal import BETA_CAL, BETA_TEST, RobustConformalCalibration
    from drake_cert.experiments.claims import conformal_miss_bounds

    def calibration(alpha_c, sigma):
        return RobustConformalCalibration({0: 0.3, 1: 0.2}, {0: 50, 1: 50}, 2, sigma, 1000,
                                          alpha_c)

    bounds = conformal_miss_bounds({("p", 0.25): calibration(0.2481, 0.25),
                                    ("p", 1.0): calibration(0.2490, 1.0),
                                    ("q", 0.5): calibration(0.2410, 0.5)})
    assert set(bounds) == {"p", "q"}
    assert abs(bounds["p"] - (0.2490 + BETA_CAL + BETA_TEST)) < 1e-12
    assert abs(bounds["q"] - (0.2410 + BETA_CAL + BETA_TEST)) < 1e-12
    assert conformal_miss_bounds({}) == {}
