"""``drake-cert simulate``: table/JSON output, plot written atomically, one-line errors."""

import dataclasses
import json

import pytest
from design_fixtures import lqr_design

from drake_cert import cli
from drake_cert.config import load_settings, load_vehicle
from drake_cert.io import provenance
from synthesis.design_io import DesignTable, save_design_table


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
