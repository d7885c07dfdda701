"""The reproduction's headline: departures counted without conditioning on the truth, with
intervals that account for departures clustering by frame."""

import csv
import hashlib
import json
from pathlib import Path

import pytest

from drake_cert.certification.statistics import clopper_pearson_one_sided
from drake_cert.errors import ConfigError
from drake_cert.experiments import headline as hl
from drake_cert.experiments.outputs import FRAME_COLUMNS
from drake_cert.experiments.tables import to_csv

PAPER = Path(__file__).resolve().parents[1] / "results" / "paper"


def episode(frame, pipeline, *, left=False, certified=True, attack="sa", eps=0.25,
            design="dry", preset="p", sigma=0.5):
    return dict(preset=preset, frame=frame, position=frame, pipeline=pipeline, attack=attack,
                eps=eps, sigma=sigma, certified=certified, left_lane=left, true_label="dry",
                design_labels=design)


def find(result, pipeline, selection=hl.ALL, preset=hl.ALL):
    return next(r for r in result["rows"] if r["pipeline"] == pipeline
                and r["selection"] == selection and r["preset"] == preset)


def test_departures_the_truth_split_would_hide_are_counted_and_f_is_beside_g():
    """g left its lane under a certified range that missed the true label: the headline counts
    it; the truth-conditioned split shows 0 for g and for f alike."""
    rows = []
    for k in range(10):
        wrong = k < 2  # two frames whose certified range misses "dry"
        rows += [episode(k, "g", left=wrong, design="grippy" if wrong else "dry+wet"),
                 episode(k, "g", attack="none", left=False),
                 episode(k, "g", certified=False, attack="ea"),  # not certified: not counted
                 episode(k, "f", certified=False, left=k < 5, design="grippy" if k < 5 else "dry")]
    result = hl.headline(rows, resamples=500)
    g, f = find(result, "g"), find(result, "f")
    assert (g["departures"], g["episodes"], g["attacked"]) == (2, 10, 20)
    assert (g["frames_departed"], g["frames"]) == (2, 10)
    assert g["certified_only"] and not f["certified_only"]
    assert (f["departures"], f["episodes"]) == (5, 10)  # f: every attacked episode
    split = hl.truth_conditioned(rows)
    assert split["g"]["holds"] == dict(departures=0, episodes=8)
    assert split["f"]["holds"] == dict(departures=0, episodes=5)
    assert split["g"]["misses"] == dict(departures=2, episodes=2)
    text = hl.markdown(result, split, main_eps=0.25, names={"g": "g (safe-set interval)"})
    assert text.startswith("**Left the lane, not conditioned on the truth**")
    assert "2 / 10 = 20.00%" in text and "g (safe-set interval)" in text
    assert "tests the controller designs, not the certificate" in text


def per_episode_cp_width(hits, total):
    lo, hi = clopper_pearson_one_sided(hits, total, 0.025)
    return float(hi - lo)


def test_departures_clustered_on_few_frames_widen_the_interval_past_per_episode_bounds():
    clustered, spread = [], []
    for k in range(40):
        clustered += [episode(k, "g", left=k < 4) for _ in range(10)]  # 4 frames, 10 each
        spread += [episode(k, "g", left=j == 0) for j in range(10)]  # one on every frame
    a = hl.headline(clustered, resamples=2000)
    b = hl.headline(spread, resamples=2000)
    wa, wb = (find(r, "g")["ci95_pct"][1] - find(r, "g")["ci95_pct"][0] for r in (a, b))
    cp = 100 * per_episode_cp_width(40, 400)
    assert find(a, "g")["pct"] == find(b, "g")["pct"] == 10.0
    assert wa > 2.0 * cp  # clustered: far wider than Clopper-Pearson over episodes
    assert wb < 0.5 * cp  # every frame alike: no more spread than frames give
    assert find(a, "g")["frames_departed"] == 4 and find(b, "g")["frames_departed"] == 40


def test_the_bootstrap_is_fixed_by_its_seed_and_stated():
    rows = [episode(k, "g", left=k % 7 == 0 and j < 3) for k in range(30) for j in range(5)]
    one, two = hl.headline(rows, resamples=300, seed=4), hl.headline(rows, resamples=300, seed=4)
    assert one == two
    assert "300 resamples, seed 4" in one["method"]
    assert "300 resamples, seed 4" in hl.markdown(one)


def test_no_departure_takes_the_exact_bound_over_frames():
    """With nothing to resample, the interval is Clopper-Pearson over frames: wider than over
    episodes, never [0, 0]."""
    rows = [episode(k, "g") for k in range(50) for _ in range(10)]
    g = find(hl.headline(rows, resamples=100), "g")
    _, up = clopper_pearson_one_sided(0, 50, 0.025)
    assert g["ci95_pct"] == pytest.approx([0.0, 100 * float(up)])
    assert g["ci95_pct"][1] > 100 * per_episode_cp_width(0, 500)
    # ... and says so: the row and the table mark that interval, the legend names it
    assert g["ci95_method"] == "clopper_pearson_frames"
    text = hl.markdown(hl.headline(rows, resamples=100))
    assert "= 0.00% [0.00, 7.11]*" in text and "* marks an episode interval" in text
    some = [episode(k, "g", left=k == 0) for k in range(50) for _ in range(10)]
    assert find(hl.headline(some, resamples=100), "g")["ci95_method"] == "cluster_bootstrap"


def test_pipelines_are_counted_by_whatever_name_they_carry():
    rows = [episode(k, name, left=(name == "g_conformal" and k == 0)) for k in range(5)
            for name in ("g", "g_conformal")]
    rows += [episode(k, "f", certified=False, preset="q") for k in range(5)]
    result = hl.headline(rows, resamples=100)
    assert {r["pipeline"] for r in result["rows"]} == {"g", "g_conformal", "f"}
    assert find(result, "g_conformal")["departures"] == 1
    assert find(result, "f", preset="q")["episodes"] == 5
    assert find(result, "g", "SA eps = 0.25", "p")["episodes"] == 5
    text = hl.markdown(result, main_eps=0.25, names=hl.display_names("safe_set"))
    assert "g (robust conformal interval, the drive's calibration)" in text
    assert "g (safe-set interval: the paper's, assumes g right on the clean frame)" in text
    assert text.index("the drive's") < text.index("safe-set interval")  # it leads


def test_frame_rows_read_back_from_csv_as_written(tmp_path):
    rows = [dict(episode(k, "g", left=k == 1), seed=f"0/0/{k}", task="classify",
                 stiffness_n_per_rad=50_000.0, friction_mu=0.6, predicted="dry",
                 interval_lo=40_000.0, interval_hi=60_000.0, interval_covers=True,
                 certificate=0.5, safe_set_radius=float("inf"), velocity_mps=12.5,
                 peak_abs_e1_m=0.2) for k in range(3)]
    path = tmp_path / "frames.csv"
    path.write_text(to_csv(rows, FRAME_COLUMNS))
    back = hl.read_frames_csv(path, rename={"g": "g_conformal"})
    assert [r["pipeline"] for r in back] == ["g_conformal"] * 3
    assert [dict(r, pipeline="g") for r in back] == rows
    # h decided sequentially has no point estimate: written "", read back as None
    regress = [dict(rows[0], task="regress", pipeline="h", predicted=v) for v in (None, 51e3)]
    path.write_text(to_csv(regress, FRAME_COLUMNS))
    assert hl.read_frames_csv(path) == regress


def test_a_missing_or_foreign_file_is_one_readable_error(tmp_path):
    with pytest.raises(ConfigError, match="cannot read frame rows"):
        hl.read_frames_csv(tmp_path / "nope.csv")
    (tmp_path / "x.csv").write_text("a,b\n1,2\n")
    with pytest.raises(ConfigError, match="not a reproduction's frames.csv: no column preset"):
        hl.read_frames_csv(tmp_path / "x.csv")


# frames.csv of results/paper as committed when its figures below were recounted
RECOUNTED_SHA256 = "a57f2c133bea4f5c1da5c30ffdc3bbd3e076878803662e1ccb7ef220d0a02623"


def _recount(rows: list[dict], pipeline: str, *, certified_only: bool,
             attack: str | None = None, eps: float | None = None) -> tuple[int, int, int, int]:
    """(departures, episodes, frames with a departure, frames) of a pipeline's attacked
    episodes, counted with the csv module alone (no project code)."""
    picked = [r for r in rows if r["pipeline"] == pipeline and r["attack"] != "none"
              and (attack is None or r["attack"] == attack)
              and (eps is None or float(r["eps"]) == eps)
              and (not certified_only or r["certified"] == "True")]
    frames = {(r["preset"], r["frame"]) for r in picked}
    departed = {(r["preset"], r["frame"]) for r in picked if r["left_lane"] == "True"}
    return (sum(r["left_lane"] == "True" for r in picked), len(picked), len(departed),
            len(frames))


def test_the_committed_reproduction_gives_the_independent_recount():
    """From results/paper/frames.csv, counted without the project's code: claims.json's
    headline and per-preset figures are the recount's; on the run committed when this test was
    written, the figures README quotes."""
    with open(PAPER / "frames.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    claims = json.loads((PAPER / "claims.json").read_text())
    presets = [p for p in claims if "g_inside_certificate" in claims[p]]
    head = {(r["pipeline"], r["selection"]): r for r in claims["headline"]["rows"]
            if r["preset"] == "all"}
    for pipeline in ("g", "g_conformal"):
        departures, episodes, frames_departed, _ = _recount(rows, pipeline, certified_only=True)
        key = f"{pipeline}_inside_certificate"
        assert departures == sum(claims[p][key]["hits"] for p in presets)
        assert episodes == sum(claims[p][key]["total"] for p in presets)
        row = head[(pipeline, hl.ALL)]
        assert (row["departures"], row["episodes"], row["frames_departed"]) == \
            (departures, episodes, frames_departed)
    f_sa = _recount(rows, "f", certified_only=False, attack="sa", eps=0.25)
    row = head[("f", "SA eps = 0.25")]
    assert (row["departures"], row["episodes"], row["frames_departed"], row["frames"]) == f_sa
    # A regenerated run still gets every check above; its quoted figures are pinned here (with
    # its frames.csv digest) when README quotes them, so only this last part waits for that.
    if hashlib.sha256((PAPER / "frames.csv").read_bytes()).hexdigest() != RECOUNTED_SHA256:
        pytest.skip("results/paper was regenerated after these figures were recounted")
    assert _recount(rows, "g", certified_only=True) == (66, 3600, 23, 300)
    assert _recount(rows, "g_conformal", certified_only=True) == (45, 3976, 12, 300)
    assert f_sa == (41, 300, 41, 300)
    # the truth-conditioned split: 0 departures where the range holds, for f as for g
    split = hl.truth_conditioned(hl.read_frames_csv(PAPER / "frames.csv"))
    assert split["g"]["holds"]["departures"] == 0
    assert split["f"]["holds"]["departures"] == 0
    # departures cluster: the bootstrap interval is wider than Clopper-Pearson over episodes
    lo, hi = head[("g", hl.ALL)]["ci95_pct"]
    assert hi - lo > 100 * per_episode_cp_width(66, 3600)  # g's departures, episodes above


def _headline_table(text: str) -> list[str]:
    """The rows of the first Markdown table in ``text``."""
    lines = text.splitlines()
    first = next(i for i, line in enumerate(lines) if line.startswith("|"))
    table = []
    for line in lines[first:]:
        if not line.startswith("|"):
            break
        table.append(line)
    return table


def test_the_results_page_quotes_the_committed_headline_row_for_row():
    """docs/results.md quotes claims.md's headline table as committed: a regenerated run that
    changes a figure fails here until the page says the same."""
    page = (PAPER.parents[1] / "docs" / "results.md").read_text()
    start = page.index("<!-- headline: results/paper/claims.md -->")
    end = page.index("<!-- /headline -->", start)
    quoted = _headline_table(page[start:end])
    assert quoted == _headline_table((PAPER / "claims.md").read_text())
    assert len(quoted) >= 4  # header, rule and at least f and g


def test_the_readme_headline_rows_are_committed_rows():
    """The README's few headline rows are rows of claims.md's table, word for word, and they
    include the certified pipeline's and the non-robust f's over every attack."""
    readme = (PAPER.parents[1] / "README.md").read_text()
    start = readme.index("<!-- headline: results/paper/claims.md -->")
    end = readme.index("<!-- /headline -->", start)
    quoted = _headline_table(readme[start:end])
    committed = _headline_table((PAPER / "claims.md").read_text())
    assert quoted[:2] == committed[:2]  # header and rule
    assert set(quoted[2:]) <= set(committed[2:])
    shown = {row.split("|")[1].strip() for row in quoted[2:]}
    assert any(name.startswith("f ") for name in shown)
    assert any("conformal" in name for name in shown)


def test_the_readme_counts_the_papers_claims_once_each_and_lists_those_that_do_not_hold():
    """README's summary of the paper's claims gives one verdict per claim at the paper's budget
    (the counts of claims.json, in its words) and names every claim that does not hold there,
    where, in claims.json's words (paper_claims.failing), and nothing else."""
    from drake_cert.experiments.paper_claims import counts_text, failing

    readme = (PAPER.parents[1] / "README.md").read_text()
    start = readme.index("<!-- failing: results/paper/claims.json -->")
    end = readme.index("<!-- /failing -->", start)
    listed = [line[2:] for line in readme[start:end].splitlines() if line.startswith("- ")]
    claims = json.loads((PAPER / "claims.json").read_text())["paper_claims"]
    assert listed == failing(claims)
    words = " ".join(readme.split())
    assert f"Of the paper's {len(claims['claims'])} checkable claims" in words
    assert counts_text(claims["counts"]) in words
    assert "Clopper-Pearson" in words and "t-interval" in words
