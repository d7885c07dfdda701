"""The perception table: f and g on the same frames, shared work identical to a cell run alone,
resumable, with coverage confidence intervals."""

from __future__ import annotations

import dataclasses

import pytest

from drake_cert.config import load_conditions
from drake_cert.experiments.perception_eval import (
    CalibrationInputs,
    EvalFrames,
    certify_classifier,
    json_safe,
    select_frames,
)
from drake_cert.experiments.perception_table import (
    DATA_SEED,
    CellReport,
    CellStore,
    TableSettings,
    cell_key,
    coverage,
    render,
    rows,
    run_preset,
)

TINY = TableSettings(frames=3, n0=32, n=200, calibration_n=100, conformal_per_class=10,
                     budgets=(0.25,), attack_steps=2, precision="fp32", compile="off",
                     tasks=("classify",))


@pytest.fixture(scope="module")
def tiny_cells(tmp_path_factory):
    store = CellStore(tmp_path_factory.mktemp("table"))
    cells = run_preset("carla-like", TINY, load_conditions(), store,
                       report=CellReport(log=lambda m: None))
    return store, cells


def test_every_cell_of_f_and_g_is_run_on_the_same_frames(tiny_cells):
    _, cells = tiny_cells
    assert sorted(cells) == sorted(cell_key("classify", m, a, 0.25)
                                   for m in ("f", "g") for a in ("none", "sa", "ea"))
    frames = {key: [(r["label"], r["stiffness_n_per_rad"]) for r in cell["records"]]
              for key, cell in cells.items()}
    assert len(set(map(tuple, frames.values()))) == 1
    assert len(next(iter(frames.values()))) == TINY.frames


def test_shared_calibration_and_clean_certificates_equal_a_cell_run_alone(tiny_cells):
    _, cells = tiny_cells
    from drake_cert.certification.seeds import frame_choice_seed
    from drake_cert.perception.datasets import load_split
    from drake_cert.perception.models import load_model

    table = load_conditions()
    model = load_model("carla-like", "classify", TINY.sigma)
    test = load_split("carla-like", "test", seed=DATA_SEED, frames_per_class=1)
    idx = select_frames(test.labels, TINY.frames, frame_choice_seed(TINY.seed))
    cal = load_split("carla-like", "calibration", seed=DATA_SEED,
                     frames_per_class=TINY.conformal_per_class)
    settings = TINY.certify("carla-like", "classify", TINY.sigma, "ea", 0.25)
    frames = EvalFrames(test.images[idx], test.labels[idx], test.stiffness_n_per_rad[idx],
                        tuple(test.label_names))
    records, _ = certify_classifier(model, frames, table, settings,
                                    inputs=CalibrationInputs(frames=(cal.images, cal.labels)))
    assert json_safe(records) == cells[cell_key("classify", "g", "ea", 0.25)]["records"]


def test_a_rerun_reads_every_cell_back_without_computing(tiny_cells):
    store, cells = tiny_cells
    computed = []
    again = run_preset("carla-like", TINY, load_conditions(), store,
                       report=CellReport(log=computed.append))
    assert computed == []
    assert again == cells


def test_rows_pair_f_and_g_and_render_with_confidence_intervals(tiny_cells):
    _, cells = tiny_cells
    r = rows(cells, TINY)
    assert [(row["attack"], row["eps"]) for row in r["classify"]] == [
        ("none", 0.25), ("sa", 0.25), ("ea", 0.25)]
    for row in r["classify"]:
        assert 0 <= row["conformal"]["ci95"][0] <= row["conformal"]["share"] \
            <= row["conformal"]["ci95"][1] <= 1
        assert row["conformal_guarantee"] == pytest.approx(0.99)
    text = render({"carla-like": r}, TINY)
    assert "| sa | 0.25 |" in text and "## carla-like" in text


def test_coverage_interval_is_clopper_pearson():
    c = coverage([{"covered": True}] * 299 + [{"covered": False}])
    assert c["covered"] == 299 and c["frames"] == 300
    assert c["ci95"][0] == pytest.approx(0.98157, abs=1e-4)  # beta.ppf(0.025, 299, 2)
    assert c["ci95"][1] == pytest.approx(0.99992, abs=1e-4)


def test_bad_budgets_are_a_config_error():
    from drake_cert.errors import ConfigError

    with pytest.raises(ConfigError, match="budgets"):
        dataclasses.replace(TINY, budgets=(0.0,)).validate()


def test_a_stored_cell_made_with_other_settings_is_recomputed(tiny_cells, tmp_path):
    import json
    import shutil

    store, cells = tiny_cells
    copy = CellStore(tmp_path / "copy")
    shutil.copytree(store.root, copy.root)
    key = cell_key("classify", "f", "sa", 0.25)
    path = copy.path("carla-like", key)
    cell = json.loads(path.read_text())
    cell["settings"]["n"] = 10_000
    path.write_text(json.dumps(cell))
    computed = []
    again = run_preset("carla-like", TINY, load_conditions(), copy,
                       report=CellReport(log=computed.append))
    assert [m.split(":")[0] for m in computed] == [f"carla-like {key}"]
    assert again[key]["records"] == cells[key]["records"]
