"""The joint gain program (one Lyapunov matrix for every design, docs/design.md 5.6) keeps a
solution whenever its matrix certifies, whatever the solver's status says, and says so."""

import json

import numpy as np
import pytest

from drake_cert import cli
from drake_cert.config import default_path, load_conditions, load_settings, load_vehicle
from drake_cert.synthesis import joint_gains
from drake_cert.synthesis.table import design_label_ranges

SETTINGS = load_settings()
CONDITIONS = load_conditions()
TALL_SUV = default_path("vehicles/tall_suv.yaml")


def _boxes(vehicle):
    scaled = CONDITIONS.with_stiffness_scale(vehicle.tire_stiffness_scale)
    return list(dict.fromkeys(joint_gains.gain_box(scaled.hull(r), scaled.least_friction(r),
                                                   SETTINGS)
                              for r in design_label_ranges(CONDITIONS)))


@pytest.fixture(scope="module")
def tall_suv():
    vehicle = load_vehicle(TALL_SUV)
    boxes = _boxes(vehicle)
    return vehicle, boxes, joint_gains.solve_common_lyapunov_gains(vehicle, boxes, SETTINGS)


def test_an_ill_conditioned_joint_program_keeps_a_solution_its_matrix_certifies(tall_suv):
    vehicle, boxes, solve = tall_suv
    assert solve.status in ("optimal", "optimal_inaccurate")  # "optimal_inaccurate" here
    assert solve.gains is not None and len(solve.gains) == len(boxes)
    assert solve.condition_number > 1e3
    assert solve.proved_rate >= SETTINGS.synthesis.decay_rate


def test_the_check_recomputes_the_rate_from_the_matrix_and_fails_a_wrong_one(tall_suv):
    vehicle, boxes, solve = tall_suv
    problem, x, ys = joint_gains._joint_program(vehicle, boxes, SETTINGS, np.ones(4))
    from drake_cert.synthesis.gains import solve_sdp_status

    solve_sdp_status(problem)
    rate = joint_gains.corner_rate(vehicle, boxes, x.value, solve.gains)
    assert rate >= SETTINGS.synthesis.decay_rate - 1e-6
    skewed = x.value @ np.diag([1.0, 1.0, 30.0, 30.0])  # not symmetric in the original sense
    skewed = 0.5 * (skewed + skewed.T)
    assert joint_gains.corner_rate(vehicle, boxes, skewed, solve.gains) < rate
    assert joint_gains.corner_rate(vehicle, boxes, -np.eye(4), solve.gains) == -np.inf


def test_gains_solved_in_scaled_coordinates_certify_in_the_original_ones():
    """The rescaled solve (z = D s): its gains k = k_z D with X = D^-1 X_z D^-1 prove the decay
    at every corner of the shipped car's boxes."""
    vehicle = load_vehicle()
    boxes = _boxes(vehicle)
    solve, x = joint_gains._solve_in(vehicle, boxes, SETTINGS, np.array([1.0, 0.5, 20.0, 4.0]))
    assert solve.rescaled and solve.gains is not None and x is not None
    assert joint_gains.corner_rate(vehicle, boxes, x, solve.gains) >= \
        SETTINGS.synthesis.decay_rate - 1e-6


def test_synthesize_says_how_the_joint_program_was_solved_and_stores_it(tmp_path, capsys):
    out = tmp_path / "tall.yaml"
    assert cli.main(["synthesize", "--vehicle", str(TALL_SUV), "--out", str(out),
                     "--json"]) == 0
    captured = capsys.readouterr()
    report = json.loads(captured.out)["provenance"]["joint_gain_solve"]
    assert report["accepted"] is True
    assert report["proved_decay_per_s"] >= SETTINGS.synthesis.decay_rate
    assert "joint gains: Clarabel" in captured.err
    if report["solver_status"] != "optimal":
        assert "kept: its matrix proves the decay" in captured.err
    assert cli.main(["verify", str(out)]) == 0
