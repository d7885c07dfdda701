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


def frame_rows(budgets=(0.25,), every_sigma_at=(), regression=False):
    """One frame per cell: f and g (g at every sigma at the first budget and at
    ``every_sigma_at``, at sigma 0.5 elsewhere), with ``regression`` f_reg and h likewise."""
    rows = []
    pipelines = (("f", (0.0,), "classify"), ("g", SIGMAS, "classify"))
    if regression:
        pipelines += (("f_reg", (0.0,), "regress"), ("h", SIGMAS, "regress"))
    for preset in PRESETS:
        for pipeline, sigmas, task in pipelines:
            for sigma in sigmas:
                for attack in ("none", "sa", "ea"):
                    for eps in budgets:
                        if attack == "none" and eps != budgets[0] or \
                                eps != budgets[0] and eps not in every_sigma_at and \
                                sigma not in (0.0, 0.5):
                            continue  # clean once; the sweep's g at sigma 0.5 only
                        rows.append(dict(preset=preset, task=task, pipeline=pipeline,
                                         sigma=sigma, attack=attack, eps=eps,
                                         predicted="a" if task == "classify" else 82000.0,
                                         true_label="a", stiffness_n_per_rad=80000.0,
                                         left_lane=attack == "sa",
                                         velocity_mps=12.0, certificate=0.4, certified=True,
                                         interval_covers=True))
    return rows


def config_for(sweep_eps, regression=False):
    return SimpleNamespace(presets=PRESETS, sigmas=SIGMAS, eps=0.25, sweep_eps=sweep_eps,
                           sweep_sigma=0.5, frames=1, n0=10, n=100, alpha=0.001, seed=0,
                           regression=regression)


@pytest.fixture(scope="module")
def full_text():
    """A run with eps = 1 cells for every pipeline and sigma, and regression (the default
    reproduction's grid, one frame a cell)."""
    rows = frame_rows((0.25, 1.0), every_sigma_at=(1.0,), regression=True)
    return tables.markdown(tables.summarize(rows, 0.25, 0), config_for((0.25, 1.0), True),
                           load_conditions())


def sections(text):
    """Each ``### `` section of ``text`` by its title."""
    return {part.splitlines()[0]: part for part in text.split("\n### ")[1:]}


@pytest.fixture(scope="module")
def text():
    return tables.markdown(tables.summarize(frame_rows(), 0.25, 0), config_for((0.0, 0.25)),
                           load_conditions())


def test_the_papers_other_metrics_never_stand_in_parentheses_beside_ours(text):
    inside = set(re.findall(r"\((\d+\.\d+)\)", text))
    same = {f"{v:.2f}" for key, paper in tables.PAPER.items() for m, v in paper.items()
            if m in tables.SAME_METRICS and key[0] in ("f_clean", "f_attack", "g_ea")}
    assert inside and inside <= same
    assert "(98.60)" in text and "(29.42)" in text
    for undefined in ("(200.00)", "(6.36)", "(0.61)", "(37.50)"):
        assert undefined not in text  # instability and tau of the paper: not ours
    main = text.split("### At the paper's budget")[0]
    for other_budget in ("(27.36)", "(29.41)"):  # f's and g's EA velocity at delta = 255
        assert other_budget not in main  # never beside ours at eps = 0.25


def test_every_paper_figure_under_attack_stands_only_at_the_papers_budget(full_text):
    """A figure the paper gives under attack is read at its own budget only (delta = 255, eps =
    1), never beside ours at another. The sections at eps = 0.25 hold only the paper's clean figures
    (Tables II, VIII); every attacked figure, Table VII's h (no attack or budget stated)
    included, stands at eps = 1."""
    by_title = sections(full_text)
    at_paper = [t for t in by_title if t.startswith("At the paper's budget: eps = 1")]
    assert len(at_paper) == 1
    for title, body in by_title.items():
        if title in at_paper:
            continue
        heads = [line for line in body.splitlines() if line.startswith("| ")]
        papers = [line for line in heads if "paper's" in line.split(" | ")[0]
                  or line.startswith("| sigma |") and "paper's" in line]
        assert all(re.search(r"Table (II|VIII), clean[;),]", line.split(" | ")[0])
                   for line in papers), (title, papers)
        assert "delta" not in "".join(heads), title
    section = by_title[at_paper[0]]
    for table in ("Table III", "Tables III / IV", "Table IV", "Table V", "Table VII",
                  "Table IX"):
        assert f"the paper's {table}" in section or f"({table}, " in section, table


def test_every_row_of_the_papers_figures_names_its_table_budget_and_unit(full_text):
    budgets = (", clean;", f", {tables.PAPER_DELTA};", ", attack and budget not stated;")
    papers = [line.split(" | ")[0] for line in full_text.splitlines()
              if line.startswith("| paper's")]
    assert len(papers) >= 20
    for title in papers:
        assert re.search(r"\(Tables? [IVX]+", title), title
        assert any(b in title for b in budgets), title
        assert any(title.endswith(f"; {unit})") for unit in tables.PAPER_UNITS.values()), title
    assert tables.PAPER_DELTA == "delta = 255, read as eps = 1"
    beside = [line.split(" | ")[0] for line in full_text.splitlines()
              if re.search(r"\(\d+\.\d+\) \|", line)]
    assert beside and all("in parentheses the paper's Table" in t for t in beside), beside


def test_the_papers_units_are_named_as_the_claims_name_them():
    from drake_cert.experiments import paper_claims

    assert tables.PAPER_UNITS["instability"] == paper_claims._INSTABILITY
    assert tables.PAPER_UNITS["velocity_mps"] == paper_claims._VELOCITY
    assert "not a share" in tables.PAPER_UNITS["instability"]
    assert "unit not stated" in tables.PAPER_UNITS["mse"]


def test_at_the_papers_budget_the_papers_figures_stand_with_their_budget(full_text):
    section = full_text.split("### At the paper's budget: eps = 1")[1].split("###")[0]
    delta = "delta = 255, read as eps = 1"
    assert f"| paper's f instability under SA (Table V, {delta}; the paper's own unit, not a " \
           "share) | 200.00 | 37.50 | 61.50 |" in section
    assert f"| paper's f accuracy under PGD, attack objective not stated (Table V, {delta}; % " \
           "of frames) | 0.00 | 80.00 | 69.00 |" in section
    assert f"| paper's g tau under SA / EA at sigma = 0.25 (Tables III / IV, {delta}; an L2 " \
           "radius, pixel scale not stated) | 0.61 / 0.61 | 1.19 / 0.57 | 2.26 / 0.55 |" \
        in section
    assert "| g sigma 0.25: label-range radius under SA / EA (L2, [0, 1] pixels) | " \
           "0.40 / 0.40 |" in section
    assert f"| paper's f_reg MSE under PGD (Table IX, {delta}; unit not stated, ours " \
           "(kN/rad)^2) | 0.440 | 0.430 | 0.450 |" in section
    assert "| f_reg MSE under SA ((kN/rad)^2) | 4.00 |" in section
    assert "| paper's h velocity at sigma = 0.5 (Table VII, attack and budget not stated; " \
           "unit not stated, ours m/s) | 16.79 | 15.93 | 15.99 |" in section


def test_a_run_without_the_papers_budget_still_shows_its_figures_there(text):
    section = text.split("### At the paper's budget: eps = 1")[1].split("###")[0]
    assert "This run did not evaluate eps = 1: ours are n/a" in section
    assert "| paper's f instability under SA (Table V, delta = 255, read as eps = 1; the " \
           "paper's own unit, not a share) | 200.00 | 37.50 | 61.50 |" in section
    assert "| f velocity under EA (m/s; in parentheses the paper's Table V, delta = 255, read " \
           "as eps = 1, unit not stated) | n/a (27.36) |" in section


def test_the_certificate_columns_say_whose_radius_they_are(text):
    sa_head = next(line for line in text.splitlines()
                   if line.startswith("| sigma | carla-like instability"))
    assert sa_head.startswith("| sigma | carla-like instability (%) | carla-like label-range "
                              "radius | rtk-like instability (%) |")
    sa = text.split("### Smoothed classifier g under SA")[1]
    row = next(line for line in sa.splitlines() if line.startswith("| 0.25 | 100.00 |"))
    assert row.split(" | ")[1:3] == ["100.00", "0.40"]  # ours only at eps = 0.25
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
    text = tables.markdown(tables.summarize(frame_rows((0.25, 1.0)), 0.25, 0),
                           config_for((0.25, 1.0)), load_conditions())
    section = text.split("### At the paper's budget: eps = 1")[1].split("###")[0]
    beside = "(m/s; in parentheses the paper's Table {}, delta = 255, read as eps = 1, unit " \
             "not stated)"
    assert f"| f velocity under EA {beside.format('V')} | 12.00 (27.36) | 12.00 (27.83) | " \
           "12.00 (25.35) |" in section
    assert f"| g sigma 0.5: velocity under EA {beside.format('IV')} | 12.00 (29.41) | " \
           "12.00 (28.10) | 12.00 (28.12) |" in section
    assert "| g sigma 0.5: instability under SA (%) / certified (%) | 100.00 / 100.00 |" \
        in section
    assert "| f instability under SA (%) | 100.00 | 100.00 | 100.00 |" in section
    assert "This run did not evaluate" not in section


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


def test_a_run_at_the_papers_budget_names_whose_figure_every_parenthesis_holds():
    config = SimpleNamespace(**dict(vars(config_for((1.0,))), eps=1.0))
    text = tables.markdown(tables.summarize(frame_rows((1.0,)), 1.0, 0), config,
                           load_conditions())
    beside = [line.split(" | ")[0] for line in text.splitlines()
              if re.search(r"\(\d+\.\d+\) \|", line)]
    assert len(beside) == 2 + 1 + 3  # Table II; f and g per sigma: EA velocity at eps = 1
    assert all("in parentheses the paper's Table" in t for t in beside), beside
    assert "stand in the section at the paper's budget, eps = 1, below" in text
