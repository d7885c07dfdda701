"""The training sweep: a model that abstains less ships only if it does not certify wrong more."""

import json

import pytest
import torch

from drake_cert import cli
from drake_cert.errors import ConfigError
from drake_cert.experiments.training_sweep import (
    SweepSettings,
    default_candidates,
    own_label_tail,
    pick_candidate,
)

SETTINGS = SweepSettings(preset="robotcar-like", sigma=1.0, budgets=(0.25, 1.0))


def _rows(wrong_025, wrong_1, abstain_sa_1, hi_025=0.03, hi_1=0.01):
    """Rows of one candidate: certified-wrong shares (with upper bounds) and the abstention of
    the ranking cell (SA at eps = sigma = 1)."""
    rows = []
    for attack in ("none", "sa"):
        for eps, wrong, hi in ((0.25, wrong_025, hi_025), (1.0, wrong_1, hi_1)):
            rows.append({"attack": attack, "eps": eps, "certified_wrong": wrong,
                         "certified_wrong_ci95": [0.0, hi],
                         "interval_abstain": abstain_sa_1 if (attack, eps) == ("sa", 1.0)
                         else 0.1})
    return rows


def test_the_pick_abstains_least_among_candidates_that_do_not_certify_wrong_more():
    results = {"baseline": _rows(0.015, 0.002, 0.34),
               "decisive": _rows(0.05, 0.002, 0.14),    # fewest abstentions, wrong at 0.25
               "careful": _rows(0.010, 0.002, 0.24),
               "timid": _rows(0.005, 0.001, 0.30)}
    choice = pick_candidate(results, SETTINGS)
    assert choice["pick"] == "careful"
    assert set(choice["eligible"]) == {"baseline", "careful", "timid"}
    assert "0.050" in choice["reasons"]["decisive"] and "eps 0.25" in choice["reasons"]["decisive"]


def test_without_a_better_candidate_the_baseline_stays():
    results = {"baseline": _rows(0.015, 0.002, 0.34), "worse": _rows(0.04, 0.002, 0.10),
               "same": _rows(0.015, 0.002, 0.34)}
    assert pick_candidate(results, SETTINGS)["pick"] == "baseline"  # ties go to the baseline


def _tail(*shares):
    return {f"label{k}": {"share": s} for k, s in enumerate(shares)}


def test_ranked_by_the_tail_the_pick_has_the_thinnest_worst_label_among_the_eligible():
    results = {"baseline": _rows(0.015, 0.002, 0.20), "thin": _rows(0.010, 0.002, 0.27),
               "thinner_but_wrong": _rows(0.05, 0.002, 0.30), "fat": _rows(0.01, 0.0, 0.10)}
    tails = {"baseline": _tail(0.12, 0.06), "thin": _tail(0.02, 0.025),
             "thinner_but_wrong": _tail(0.0, 0.0), "fat": _tail(0.01, 0.20)}
    by_tail = SweepSettings(preset="robotcar-like", sigma=1.0, budgets=(0.25, 1.0), rank="tail")
    assert pick_candidate(results, by_tail, tails)["pick"] == "thin"
    assert pick_candidate(results, SETTINGS, tails)["pick"] == "fat"  # by abstentions
    with pytest.raises(ConfigError, match="own-label tail"):
        pick_candidate(results, by_tail)
    with pytest.raises(ConfigError, match="rank 'speed'"):
        SweepSettings(preset="robotcar-like", sigma=1.0, rank="speed")


def test_the_tail_counts_the_frames_g_gives_under_half_their_own_votes():
    records = [{"label": 0, "clean_own_share": s} for s in (0.2, 0.49, 0.5, 0.9)] + \
              [{"label": 1, "clean_own_share": 1.0}]
    tail = own_label_tail(records, ["sunny", "snow"])
    assert tail["sunny"]["under_half"] == 2 and tail["sunny"]["share"] == 0.5
    assert tail["sunny"]["lowest"] == 0.2 and tail["snow"]["share"] == 0.0
    lo, hi = tail["sunny"]["share_ci95"]
    assert lo < 0.5 < hi


def test_the_grid_names_each_method_and_width():
    names = [c.name for c in default_candidates((10.0,), ((0.25, 0.5),), (16, 8))]
    assert names == ["baseline", "consistency_l10", "tail_q0.25_b0.5_w16", "consistency_l10_w8",
                     "tail_q0.25_b0.5_w8"]
    with pytest.raises(ConfigError, match="q must be in"):
        default_candidates((), ((0.0, 0.5),))
    pooled = default_candidates((), ((0.25, 0.75),), (8,), (1, 2))
    assert [(c.name, c.train_options[-4:]) for c in pooled[1:]] == [
        ("tail_q0.25_b0.75_w8", ("--tail-weight", "0.75", "--width", "8")),
        ("tail_q0.25_b0.75_w8_p2", ("--width", "8", "--pool", "2"))]


def test_a_ranking_cell_outside_the_sweep_is_a_config_error():
    with pytest.raises(ConfigError, match="ranking cell"):
        SweepSettings(preset="robotcar-like", sigma=1.0, budgets=(0.25,))
    with pytest.raises(ConfigError, match="sigma must be > 0"):
        SweepSettings(preset="robotcar-like", sigma=0.0)


def test_the_sweep_trains_certifies_writes_and_resumes(tmp_path, capsys):
    before = torch.get_num_threads()
    root = tmp_path / "sweep"
    argv = ["sweep", "--preset", "rtk-like", "--sigma", "0.25", "--lambdas", "none",
            "--tails", "0.5:0.5", "--widths", "4", "--rank", "tail", "--frames", "3",
            "--n", "50", "--n0", "10", "--epochs", "1",
            "--frames-per-class", "6", "--root", str(root)]
    try:
        assert cli.main(argv) == 0
        out = json.loads((root / "sweep.json").read_text())
        assert set(out["results"]) == {"baseline", "tail_q0.5_b0.5_w4"}
        assert set(out["tails"]["baseline"]) == {"asphalt", "cobblestone", "sand"}
        for rows in out["results"].values():
            assert [(r["attack"], r["eps"]) for r in rows] == [("none", 0.25), ("sa", 0.25)]
            for r in rows:
                assert r["certified_right"] + r["certified_wrong"] + r["interval_abstain"] == \
                    pytest.approx(1.0)
        assert out["choice"]["pick"] in out["results"]
        assert (root / "sweep.png").stat().st_size > 0
        text = (root / "sweep.md").read_text()
        assert "tail, fraction 0.5, weight 0.5, width 4" in text and "Own-label tail" in text
        assert "thinnest worst-label tail" in text
        stored = root / "tail_q0.5_b0.5_w4.eval.json"
        mtime = stored.stat().st_mtime_ns
        capsys.readouterr()
        assert cli.main(argv) == 0  # everything stored: nothing trained or certified again
        assert stored.stat().st_mtime_ns == mtime
        assert "drake-cert train" not in capsys.readouterr().err
    finally:
        torch.set_num_threads(before)


@pytest.mark.parametrize("extra, message", [(["--sigma", "0"], "sigma must be > 0"),
                                            (["--sigma", "0.25", "--lambdas", "x"], "'x'"),
                                            (["--sigma", "0.25", "--tails", "0.25"], "q:beta"),
                                            (["--sigma", "0.25", "--widths", "0"],
                                             "between 2 and 256"),
                                            (["--sigma", "0.25", "--pools", "3"],
                                             "pixel-block sizes from")])
def test_bad_sweep_options_give_one_line(tmp_path, capsys, extra, message):
    argv = ["sweep", "--preset", "rtk-like", "--root", str(tmp_path), *extra]
    try:
        code = cli.main(argv)
    except SystemExit as e:  # argparse's usage errors exit 2 from inside main
        code = e.code
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0], err
