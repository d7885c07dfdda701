"""The paper's claims, one verdict each at its budget: each verdict follows the rows, ties and
an attack that does not move the baseline are 'not informative', never 'holds', and the
committed claims.json is what the code gives on the committed frames."""

import json
import math
import re
from pathlib import Path

import pytest

from drake_cert.experiments import paper_claims as pc
from drake_cert.experiments.claims import claims_document, document_markdown, preset_claims
from drake_cert.experiments.headline import read_frames_csv

PAPER = Path(__file__).resolve().parents[1] / "results" / "paper"
N = 100  # frames per preset
SIGMAS = (0.25, 0.5)
# What the rows show by default, chosen so that every claim of the paper holds with its
# interval apart: a share is the first fraction of a preset's frames.
WORLD = dict(f_clean_left=0.0, f_sa_left={"carla-like": 1.0, "rtk-like": 0.5,
                                          "robotcar-like": 1.0},
             f_ea_v=7.0, g_ea_v=9.0, g_other_sigma_left=0.2, f_reg_clean_left=0.0,
             f_reg_sa_left=0.5, h_left=0.0, h_ea_v=9.0)


def row(preset, position, pipeline, attack, *, sigma=0.0, left=False, v=10.0, predicted="dry",
        certified=False):
    regress = pipeline in ("f_reg", "h")
    return dict(preset=preset, position=position, frame=position, true_label="dry",
                pipeline=pipeline, sigma=sigma, attack=attack, eps=1.0, left_lane=left,
                velocity_mps=v, certified=certified, predicted=predicted,
                task="regress" if regress else "classify", design_labels="dry",
                interval_covers=True, stiffness_n_per_rad=100e3)


def preset_rows(preset, world):
    """One preset's rows at eps = 1 (clean rows too), as ``world`` says."""
    def first(share, i):
        return i < round(share * N)
    best = pc.PAPER_BEST_SIGMA[preset]
    out = []
    for i in range(N):
        sa_left = world["f_sa_left"][preset] if isinstance(world["f_sa_left"], dict) \
            else world["f_sa_left"]
        out += [row(preset, i, "f", "none", left=first(world["f_clean_left"], i)),
                row(preset, i, "f", "sa", left=first(sa_left, i), predicted="wet"),
                row(preset, i, "f", "ea", v=world["f_ea_v"], predicted="wet"),
                row(preset, i, "f_reg", "none", left=first(world["f_reg_clean_left"], i),
                    predicted=101e3),
                row(preset, i, "f_reg", "sa", left=first(world["f_reg_sa_left"], i),
                    predicted=150e3),
                row(preset, i, "f_reg", "ea", v=6.0, predicted=50e3)]
        for s in SIGMAS:
            g_left = 0.0 if s == best else world["g_other_sigma_left"]
            out += [row(preset, i, "g", "none", sigma=s, certified=True),
                    row(preset, i, "g", "sa", sigma=s, left=first(g_left, i), certified=True),
                    row(preset, i, "g", "ea", sigma=s, v=world["g_ea_v"], certified=True),
                    row(preset, i, "h", "sa", sigma=s, left=first(world["h_left"], i),
                        predicted=100e3, certified=True),
                    row(preset, i, "h", "ea", sigma=s, v=world["h_ea_v"], predicted=100e3)]
    return out


def judged(presets=pc.PRESETS, **changes):
    world = dict(WORLD, **changes)
    rows = [r for p in presets for r in preset_rows(p, world)]
    return {c["claim"]: c for c in pc.paper_claims(rows)["claims"]}


def test_every_claim_of_the_paper_holds_on_rows_that_show_it():
    claims = judged()
    assert set(claims) == set(pc.CLAIMS)
    assert {k: c["verdict"] for k, c in claims.items() if c["verdict"] != pc.HOLDS} == {}
    assert claims["f_stable_clean"]["eps"] is None  # a clean claim
    assert claims["g_less_unstable_than_f_under_sa"]["pipeline"] == "g"


def test_a_budget_the_run_did_not_evaluate_is_not_tested_and_stays_a_secondary_row():
    claims = judged()
    secondary = [s for c in claims.values() for s in c["secondary"] if s["eps"] == 0.25]
    assert secondary and all(s["verdict"] == pc.NOT_TESTED for s in secondary)
    conformal = [s for c in claims.values() for s in c["secondary"]
                 if s["pipeline"] == "g_conformal"]
    assert conformal == []  # the rows hold no g_conformal: no row for it
    doc = pc.paper_claims([r for p in pc.PRESETS for r in preset_rows(p, WORLD)])
    assert sum(doc["counts"].values()) == len(pc.CLAIMS)  # one vote per claim


def test_one_clean_departure_of_f_fails_table_two_on_that_preset_only():
    rows = [r for p in pc.PRESETS for r in preset_rows(p, WORLD)]
    for r in rows:
        if (r["preset"], r["position"], r["pipeline"], r["attack"]) == \
                ("carla-like", 7, "f", "none"):
            r["left_lane"] = True
    doc = pc.paper_claims(rows)
    claim = next(c for c in doc["claims"] if c["claim"] == "f_stable_clean")
    assert claim["verdict"] == pc.FAILS
    assert [r["verdict"] for r in claim["rows"]] == [pc.FAILS, pc.HOLDS, pc.HOLDS]
    assert pc.failing(doc) == ["f never leaves its lane without attack (Table II: instability "
                               "0.00): fails on carla-like"]


def test_rtk_is_not_the_least_vulnerable_where_another_set_leaves_its_lane_as_rarely():
    tied = judged(f_sa_left={"carla-like": 1.0, "rtk-like": 0.5, "robotcar-like": 0.5})
    assert tied["rtk_least_vulnerable"]["verdict"] == pc.FAILS_NS
    assert [r["where"] for r in tied["rtk_least_vulnerable"]["rows"]] == \
        ["rtk-like vs carla-like", "rtk-like vs robotcar-like"]
    worse = judged(f_sa_left={"carla-like": 0.1, "rtk-like": 0.5, "robotcar-like": 1.0})
    assert worse["rtk_least_vulnerable"]["verdict"] == pc.FAILS
    nobody = judged(f_sa_left=0.0)
    assert nobody["rtk_least_vulnerable"]["verdict"] == pc.NOT_INFORMATIVE
    assert nobody["f_unstable_under_sa"]["verdict"] == pc.FAILS_NS  # 0 and 0: SA did nothing


def test_g_slower_than_f_under_ea_fails_and_an_ea_that_does_not_slow_f_is_not_informative():
    slow_g = judged(g_ea_v=6.5)  # f drives 7.0 under EA
    assert slow_g["g_at_least_as_fast_as_f_under_ea"]["verdict"] == pc.FAILS
    weak = judged(f_ea_v=10.0, g_ea_v=6.5)  # EA leaves f at its clean 10.0 m/s
    assert weak["f_slower_under_ea"]["verdict"] == pc.FAILS
    assert weak["g_at_least_as_fast_as_f_under_ea"]["verdict"] == pc.NOT_INFORMATIVE
    same = judged(g_ea_v=7.0)  # g and f at the same speed on every frame
    assert same["g_at_least_as_fast_as_f_under_ea"]["verdict"] == pc.NOT_INFORMATIVE
    by_sigma = slow_g["g_at_least_as_fast_as_f_under_ea"]["rows"][0]["figures"][
        "ea_minus_baseline_by_sigma"]
    assert by_sigma["0.25"]["mean"] == pytest.approx(-0.5)


def test_h_as_fast_as_f_reg_and_h_in_lane_need_an_attack_that_moves_f_reg():
    assert judged(h_ea_v=6.0)["h_at_least_as_fast_as_f_reg_under_ea"]["verdict"] == \
        pc.NOT_INFORMATIVE  # f_reg drives 6.0 under EA too, on every frame
    assert judged(h_ea_v=5.0)["h_at_least_as_fast_as_f_reg_under_ea"]["verdict"] == pc.FAILS
    calm = judged(f_reg_sa_left=0.0)  # SA moves no f_reg episode out of its lane
    assert calm["h_stable_under_sa"]["verdict"] == pc.NOT_INFORMATIVE
    assert judged(h_left=0.01)["h_stable_under_sa"]["verdict"] == pc.FAILS


def test_a_sigma_ablation_where_every_sigma_ties_is_not_informative():
    ties = judged(g_other_sigma_left=0.0)
    assert ties["sigma_ablation_best_sigma"]["verdict"] == pc.NOT_INFORMATIVE
    assert ties["g_less_unstable_than_f_under_sa"]["verdict"] == pc.HOLDS
    close = judged(g_other_sigma_left=0.02)  # 2 of 100 against 0 of 100: intervals overlap
    assert close["sigma_ablation_best_sigma"]["verdict"] == pc.HOLDS_NS


def test_a_direction_without_separated_intervals_holds_only_not_significantly():
    v = judged(f_reg_clean_left=0.05, f_reg_sa_left=0.15)
    assert v["f_reg_unstable_under_sa"]["verdict"] == pc.HOLDS_NS
    assert v["f_reg_stable_clean"]["verdict"] == pc.FAILS


def test_paired_differences_carry_a_student_t_interval_and_verdicts_read_it():
    d = pc.paired_difference({0: 3.0, 1: 5.0, 2: 4.0}, {0: 1.0, 1: 1.0, 2: 1.0})
    assert d["mean"] == pytest.approx(3.0)
    half = 4.302652729911275 * 1.0 / math.sqrt(3)  # t(0.975, 2) * sd / sqrt(n)
    assert d["ci95"] == pytest.approx([3.0 - half, 3.0 + half])
    assert pc.interval_verdict(d, strict=True) == pc.HOLDS
    straddles = dict(d, mean=0.5, ci95=[-1.0, 2.0])
    assert pc.interval_verdict(straddles, strict=True) == pc.HOLDS_NS
    assert pc.interval_verdict(dict(d, mean=-0.5, ci95=[-2.0, 1.0]), strict=False) == \
        pc.FAILS_NS
    zero = pc.paired_difference({0: 1.0, 1: 1.0}, {0: 1.0, 1: 1.0})
    assert zero["identical"] and pc.interval_verdict(zero, strict=True) == pc.FAILS


def test_a_claim_holds_where_every_part_holds():
    assert pc.worst([pc.HOLDS, pc.HOLDS_NS]) == pc.HOLDS_NS
    assert pc.worst([pc.HOLDS, pc.NOT_INFORMATIVE]) == pc.NOT_INFORMATIVE
    assert pc.worst([pc.NOT_INFORMATIVE, pc.FAILS_NS, pc.HOLDS]) == pc.FAILS_NS
    assert pc.worst([]) == pc.NOT_TESTED


# The paper's tables, numbered in the order of their captions, and its sections.
PAPER_TABLES = {"I": "ground truth cornering stiffness", "II": "f clean: accuracy, instability, "
                "velocity", "III": "g's instability under SA per sigma", "IV": "g's velocity "
                "under EA per sigma", "V": "f under attack", "VI": "safe sets", "VII": "h",
                "VIII": "f_reg clean", "IX": "f_reg under attack"}
PAPER_SECTIONS = ("I", "II", "III", "IV", "V", "VI", "VII")  # VI: Experiments


def test_every_citation_names_a_table_or_section_the_paper_has():
    cited = {name: c.cite for name, c in pc.CLAIMS.items()}
    for name, cite in cited.items():
        for numeral in re.findall(r"Tables? ([IVX]+)(?: and ([IVX]+))?", cite):
            assert all(n in PAPER_TABLES for n in numeral if n), (name, cite)
        assert all(s == "VI" for s in re.findall(r"Section ([IVX]+)", cite)), (name, cite)
    assert cited["f_stable_clean"].startswith("Table II")
    assert cited["f_accuracy_drops_under_attack"].startswith("Tables II and V")
    assert cited["h_stable_under_sa"].startswith("Table VII")
    assert "Tables IV and V" in cited["g_at_least_as_fast_as_f_under_ea"]


def test_the_papers_figures_stand_at_its_budget_only_and_name_their_unit():
    rows = [r for p in pc.PRESETS for r in preset_rows(p, WORLD)]
    at_paper = {c["claim"]: c for c in pc.paper_claims(rows)["claims"]}
    assert at_paper["f_slower_under_ea"]["paper"]["figures"]["rtk-like"] == "28.45 -> 27.83"
    assert "not a share" in at_paper["f_unstable_under_sa"]["paper"]["unit"]
    assert "unit not stated" in at_paper["f_slower_under_ea"]["paper"]["unit"]
    elsewhere = pc.paper_claims([dict(r, eps=0.25) for r in rows], main_eps=0.25,
                                secondary_eps=())
    assert all(c["paper"] == {} for c in elsewhere["claims"])


def test_the_ea_attack_strength_shows_f_clean_and_under_ea_at_each_budget():
    rows = [r for r in preset_rows("robotcar-like", WORLD)]
    strength = pc.ea_attack_strength(rows)[0]
    assert strength["clean_mps"] == 10.0 and strength["floor_mps"] == 7.0
    at_one = strength["ea_by_eps"]["1"]
    assert at_one["slowdown_mps"]["mean"] == pytest.approx(3.0)
    assert at_one["of_possible"] == pytest.approx(1.0)  # every frame at the slowest label
    assert at_one["accuracy"]["hits"] == 0
    assert "How much the efficiency attack moves f" in pc.strength_markdown([strength])


def test_claims_json_and_claims_md_carry_one_verdict_per_claim_with_its_secondary_rows():
    rows = [r for p in pc.PRESETS for r in preset_rows(p, WORLD)]
    doc = claims_document(rows, 0.25, resamples=100)
    assert "paper_claims" in doc and "paper_claims" not in preset_claims(doc)
    text = document_markdown(doc, 0.25)
    assert "one verdict each at the paper's budget" in text
    assert f"{len(pc.CLAIMS)} claims" in text and "| secondary |" in text


def test_the_committed_claims_json_is_what_the_code_gives_on_the_committed_frames():
    """claims.json's verdicts are those of paper_claims on frames.csv (rows rounded to the
    csv's digits: no verdict sits that close to its boundary)."""
    stored = json.loads((PAPER / "claims.json").read_text())["paper_claims"]
    fresh = pc.paper_claims(read_frames_csv(PAPER / "frames.csv"))
    assert [(c["claim"], c["verdict"], [r["verdict"] for r in c["rows"]],
             [s["verdict"] for s in c["secondary"]]) for c in stored["claims"]] == \
        [(c["claim"], c["verdict"], [r["verdict"] for r in c["rows"]],
          [s["verdict"] for s in c["secondary"]]) for c in fresh["claims"]]
    assert stored["counts"] == fresh["counts"]
