"""``drake-cert simulate``: table/JSON output, plot written atomically, one-line errors."""

import dataclasses
import json

import pytest
from design_fixtures import lqr_design

from drake_cert import cli
from drake_cert.config import load_settings, load_vehicle
from drake_cert.io import provenance
from drake_cert.synthesis.design_io import DesignTable, save_design_table


@pytest.fixture(scope="module")
def designs_file(tmp_path_factory):
    car = load_vehicle()
    good = lqr_design(car, 40_000.0, 60_000.0, 12.0, labels=("heavy_rain",))
    stopped = dataclasses.replace(lqr_design(car, 20_000.0, 40_000.0, 8.0, labels=("snow",)),
                                  speed_mps=0.0, failed_condition="l1_condition")
    path = tmp_path_factory.mktemp("designs") / "designs.yaml"
    save_design_table(path, DesignTable([good, stopped], car, load_settings(), provenance(0)))
    return path


def test_help_lists_the_options(capsys):
    with pytest.raises(SystemExit) as exit_info:
        cli.main(["simulate", "--help"])
    assert exit_info.value.code == 0
    out = capsys.readouterr().out
    for option in ("--designs", "--labels", "--plant", "--law", "--stiffness", "--plot", "--json"):
        assert option in out


def test_json_results_and_plot(designs_file, tmp_path, capsys):
    plot = tmp_path / "out" / "loop.png"
    code = cli.main(["simulate", "--designs", str(designs_file), "--plant", "linear_sampled",
                     "--duration", "3", "--stiffness", "ends", "--json", "--plot", str(plot)])
    assert code == 0
    result = json.loads(capsys.readouterr().out)
    cases = result["cases"]
    assert [c["stiffness_n_per_rad"] for c in cases] == [40_000.0, 60_000.0]
    for c in cases:
        assert c["labels"] == ["heavy_rain"] and c["speed_mps"] == 12.0
        assert c["left_lane"] is False and 0.0 <= c["peak_abs_e1_m"] < c["lane_margin_m"]
    assert result["skipped"][0]["labels"] == ["snow"]
    assert "l1_condition" in result["skipped"][0]["reason"]
    assert result["provenance"]["schema_version"] >= 1
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_table_names_each_case(designs_file, capsys):
    code = cli.main(["simulate", "--designs", str(designs_file), "--labels", "heavy_rain",
                     "--plant", "linear_sampled", "--duration", "2", "--speed", "25"])
    assert code == 0
    out = capsys.readouterr().out
    assert "peak|e1|" in out and "heavy_rain" in out and "25.00" in out


@pytest.mark.parametrize("argv, message", [
    (["--designs", "/nonexistent/designs.yaml"], "cannot read"),
    (["--labels", "tarmac"], "no design for this label range"),
    (["--design-index", "7"], "out of range"),
    (["--stiffness", "grippy"], "--stiffness"),
    (["--speed", "-3"], "--speed"),
    (["--plant", "linear_sampled", "--law", "gradient"], "piecewise_constant"),
])
def test_user_mistakes_give_one_line_and_exit_2(designs_file, capsys, argv, message):
    if "--designs" not in argv:
        argv = ["--designs", str(designs_file), *argv]
    code = cli.main(["simulate", *argv])
    err = capsys.readouterr().err
    assert code == 2
    assert message in err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err


def test_a_too_fast_run_reports_when_it_left_the_lane_not_a_distorted_peak(designs_file, capsys):
    code = cli.main(["simulate", "--designs", str(designs_file), "--labels", "heavy_rain",
                     "--speed", "30", "--duration", "20", "--json"])
    assert code == 0
    (case,) = json.loads(capsys.readouterr().out)["cases"]
    assert case["stopped_early"] is True and case["left_lane"] is True
    assert 0.0 < case["time_left_lane_s"] < case["simulated_s"] < 20.0
    assert case["peak_abs_e1_m"] < 5.1  # the peak up to the stop (|e1| > 5 m), no overshoot
    assert case["real_time_factor"] == pytest.approx(case["simulated_s"] / case["wall_s"])


def test_out_writes_the_tape_as_csv_or_npz(designs_file, tmp_path, capsys):
    import numpy as np

    csv_path, npz_path = tmp_path / "t" / "tape.csv", tmp_path / "tape.npz"
    for path in (csv_path, npz_path):
        assert cli.main(["simulate", "--designs", str(designs_file), "--plant",
                         "linear_sampled", "--duration", "1", "--stiffness", "ends",
                         "--out", str(path), "--json"]) == 0
        cases = json.loads(capsys.readouterr().out)["cases"]
    table = np.genfromtxt(csv_path, delimiter=",", names=True, comments="#")
    npz = np.load(npz_path)
    assert sorted(set(table["case"])) == [0.0, 1.0] and list(np.unique(npz["case"])) == [0, 1]
    assert np.allclose(table["e1_m"], npz["e1_m"], atol=1e-8)
    assert table["t_s"][-1] == pytest.approx(cases[-1]["simulated_s"])
    headers = json.loads(str(npz["cases_json"]))
    assert [h["stiffness_n_per_rad"] for h in headers] == [40_000.0, 60_000.0]
    assert "# case 1:" in csv_path.read_text()


@pytest.mark.parametrize("road", ["curve", "s_curve", "curvature_step", "straight"])
def test_each_road_kind_runs_and_is_reported(designs_file, capsys, road):
    assert cli.main(["simulate", "--designs", str(designs_file), "--plant", "linear_sampled",
                     "--duration", "2", "--road", road, "--radius", "80",
                     "--initial-offset", "0.3", "--json"]) == 0
    (case,) = json.loads(capsys.readouterr().out)["cases"]
    assert case["road"] == road and case["radius_m"] == 80.0
    assert case["initial_offset_m"] == pytest.approx(0.3)
    assert case["stopped_early"] is False and case["time_left_lane_s"] is None


def test_what_synthesize_prints_is_what_labels_accepts(tmp_path, capsys):
    from drake_cert.cli.synthesize import format_table

    car = load_vehicle()
    two = lqr_design(car, 40_000.0, 80_000.0, 10.0, labels=("light_rain", "heavy_rain"))
    path = tmp_path / "two.yaml"
    save_design_table(path, DesignTable([two], car, load_settings(), provenance(0)))
    printed = format_table([two]).splitlines()[1].split()[0]
    assert printed == "light_rain+heavy_rain"
    assert cli.main(["simulate", "--designs", str(path), "--labels", printed,
                     "--plant", "linear_sampled", "--duration", "1"]) == 0
    assert printed in capsys.readouterr().out
