"""tables.md sets beside ours only the paper's numbers of the same metric at the same budget;
the rest stand in their own rows and columns, and the header says what the data, budget and
columns are."""

import re
from types import SimpleNamespace

import pytest

from drake_cert.config import load_conditions
from drake_cert.experiments import tables

PRESETS = ("carla-like", "rtk-like", "robotcar-like")
SIGMAS = (0.25, 0.5, 1.0)


def frame_rows(budgets=(0.25,)):
    rows = []
    for preset in PRESETS:
        for pipeline, sigmas in (("f", (0.0,)), ("g", SIGMAS)):
            for sigma in sigmas:
                for attack in ("none", "sa", "ea"):
                    for eps in budgets:
                        if attack == "none" and eps != budgets[0] or \
                                eps != budgets[0] and pipeline == "g" and sigma != 0.5:
                            continue  # clean once; the sweep's g at sigma 0.5 only
                        rows.append(dict(preset=preset, task="classify", pipeline=pipeline,
                                         sigma=sigma, attack=attack, eps=eps, predicted="a",
                                         true_label="a", left_lane=attack == "sa",
                                         velocity_mps=12.0, certificate=0.4, certified=True,
                                         interval_covers=True))
    return rows


@pytest.fixture(scope="module")
def text():
    config = SimpleNamespace(presets=PRESETS, sigmas=SIGMAS, eps=0.25, sweep_eps=(0.0, 0.25),
                             sweep_sigma=0.5, frames=1, n0=10, n=100, alpha=0.001, seed=0,
                             regression=False)
    return tables.markdown(tables.summarize(frame_rows(), 0.25, 0), config, load_conditions())


def test_the_papers_other_metrics_never_stand_in_parentheses_beside_ours(text):
    inside = set(re.findall(r"\((\d+\.\d+)\)", text))
    same = {f"{v:.2f}" for key, paper in tables.PAPER.items() for m, v in paper.items()
            if m in tables.SAME_METRICS and key[0] == "f_clean"}
    assert inside and inside <= same  # at eps = 0.25: only the clean ones, e.g. (98.60)
    assert "(98.60)" in text and "(29.42)" in text
    for other_budget in ("(27.36)", "(29.41)"):  # f's and g's EA velocity at delta = 255
        assert other_budget not in text
    assert "| paper's velocity under PGD (m/s, delta = 255: another budget) | 27.36 |" in text
    for undefined in ("(200.00)", "(6.36)", "(0.61)", "(37.50)"):
        assert undefined not in text  # instability and tau of the paper: not ours
    assert "| paper's instability under SA | 200.00 | 37.50 | 61.50 |" in text


def test_the_certificate_columns_say_whose_radius_they_are(text):
    sa_head = next(line for line in text.splitlines()
                   if line.startswith("| sigma | carla-like instability"))
    assert "carla-like label-range radius | carla-like paper's instability (delta 255) | " \
           "carla-like paper's tau" in sa_head
    sa = text.split("### Smoothed classifier g under SA")[1]
    row = next(line for line in sa.splitlines() if line.startswith("| 0.25 | 100.00 |"))
    assert row.split(" | ")[1:5] == ["100.00", "0.40", "6.36", "0.61"]  # ours, ours, paper's
    assert "radius of the predicted label's safe set" in text


def test_the_header_names_the_synthetic_presets_and_the_papers_budget(text):
    first = text.splitlines()[0]
    assert first.startswith("**Data: synthetic presets.**")
    assert "procedurally generated 64x64 RGB frames standing in for the paper's CARLA, RTK and " \
           "RobotCar" in first
    assert "delta = 255" in text and "delta = 255 is eps = 1 here" in text
    assert "a budget this run did not evaluate" in text  # this sweep stops at 0.25


def test_labels_and_friction_not_in_the_papers_table_are_flagged(text):
    assert "| robotcar-like | rain | 40-80 | not in the paper |" in text
    assert "| carla-like | sunny | 80-120 | 80-120 | 0.9 |" in text
    assert "sunny, snow (ours adds rain, not in the paper)" in text
    assert "friction mu per label (the paper gives only cornering stiffness" in text
    assert "robotcar-like rain (not in, or not as in, the paper's Table I)" in text


def test_at_the_papers_budget_its_attacked_velocities_stand_beside_ours():
    config = SimpleNamespace(presets=PRESETS, sigmas=SIGMAS, eps=0.25, sweep_eps=(0.25, 1.0),
                             sweep_sigma=0.5, frames=1, n0=10, n=100, alpha=0.001, seed=0,
                             regression=False)
    text = tables.markdown(tables.summarize(frame_rows((0.25, 1.0)), 0.25, 0), config,
                           load_conditions())
    section = text.split("### At the paper's budget: eps = 1")[1].split("###")[0]
    assert "| f velocity under EA (m/s) | 12.00 (27.36) | 12.00 (27.83) | 12.00 (25.35) |" \
        in section
    assert "| g sigma 0.5: velocity under EA (m/s) | 12.00 (29.41) | 12.00 (28.10) | " \
        "12.00 (28.12) |" in section
    assert "| g sigma 0.5: instability under SA (%) / certified (%) | 100.00 / 100.00 |" \
        in section
    assert "| f instability under SA (%) | 100.00 | 100.00 | 100.00 |" in section
    assert "| paper's f instability under SA | 200.00 | 37.50 | 61.50 |" in section


def test_g_has_a_clean_table_with_instability_velocity_and_certified_share(text):
    section = text.split("### Smoothed classifier g, clean (no attack)")[1].split("###")[0]
    assert "carla-like instab. (%) | carla-like vel. (m/s) | carla-like certified (%)" in section
    assert "| 0.25 | 0.00 | 12.00 | 100.00 |" in section


def test_a_cell_decided_sequentially_has_no_mse_but_its_other_metrics():
    """h's sequential median decision certifies an interval holding the median without
    estimating it: such a cell's MSE is nan, not a crash, and a cell with point estimates
    averages only those."""
    import math

    def row(predicted, left):
        return dict(preset="carla-like", task="regress", pipeline="h", sigma=0.5,
                    attack="sa", eps=0.25, predicted=predicted, true_label="dry",
                    stiffness_n_per_rad=80000.0, left_lane=left, velocity_mps=14.0,
                    certificate=0.0, certified=True, interval_covers=True)

    decided, = tables.summarize([row(None, False), row(None, True)], 0.25, 0)
    assert math.isnan(decided["mse"]) and decided["instability_pct"] == 50.0
    mixed, = tables.summarize([row(82000.0, False), row(None, False)], 0.25, 0)
    assert mixed["mse"] == 4.0  # (2 kN/rad)^2 from the one estimate
