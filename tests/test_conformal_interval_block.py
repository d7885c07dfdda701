"""The certified-interval block with the robust conformal interval (DESIGN 3.6) in the Diagram:
where the smoothed classifier is confidently wrong, the safe-set interval misses the true
stiffness and the conformal one keeps it."""

import numpy as np
import pytest

from drake_cert.certification.classifier import ClassCertificate
from drake_cert.certification.conformal import RobustConformalCalibration
from drake_cert.certification.statistics import clopper_pearson_bounds, safe_set_radius
from drake_cert.config import load_conditions, load_settings, load_vehicle
from drake_cert.synthesis.selection import preset_designs
from drake_cert.synthesis.table import synthesize_table
from drake_cert.systems.certified_interval import CertifiedInterval, IntervalInputs
from drake_cert.systems.perception_smoothing import PerceptionResult
from drake_cert.systems.scenario import PerceptionSettings

PRESET, SIGMA, EPS = "carla-like", 0.25, 0.25
PERCEPTION = PerceptionSettings(preset=PRESET, sigma=SIGMA, eps=EPS)


@pytest.fixture(scope="module")
def designs():
    conditions = load_conditions()
    table = synthesize_table(load_vehicle(), conditions, load_settings())
    return preset_designs(table, conditions, PRESET)


def result_with_votes(counts, true_label: int, stiffness: float) -> PerceptionResult:
    counts = np.asarray(counts, dtype=np.int64)
    p_low, p_up = clopper_pearson_bounds(counts, 0.001)
    top = int(np.argmax(counts))
    radius = safe_set_radius(p_low, p_up, (top,), SIGMA)
    cert = ClassCertificate(label=top, radius=radius, labels=(top,), top_label=top, counts=counts,
                            p_low=p_low, p_up=p_up, sigma=SIGMA, alpha=0.001)
    return PerceptionResult(time_s=0.0, tick=0, position_m=40.0, frame_ok=True, error="",
                            mode="certified", task="classify", certificate=cert, base_label=top,
                            label_index=true_label, stiffness_n_per_rad=stiffness,
                            friction_mu=0.7)


def test_a_confidently_wrong_vote_keeps_the_true_stiffness_only_with_the_conformal_interval(
        designs):
    conditions = load_conditions()
    # Calibration said: light-rain frames give light rain at least 5% of the votes.
    calibration = RobustConformalCalibration(thresholds={0: 0.5, 1: 0.05, 2: 0.5},
                                             frames_per_label={0: 150, 1: 150, 2: 150},
                                             num_classes=3, sigma=SIGMA, n=1000)
    # A light-rain frame (74.8 kN/rad) that g calls sunny with 90% of the votes.
    p = result_with_votes([900, 100, 0], true_label=1, stiffness=74_800.0)
    safe_set = CertifiedInterval(designs, conditions, PERCEPTION).request(p)
    conformal = CertifiedInterval(designs, conditions, PERCEPTION,
                                  inputs=IntervalInputs(conformal=calibration)).request(p)
    lo, hi = safe_set.interval
    assert not lo <= 74_800.0 <= hi  # the safe-set interval trusts g and misses
    lo, hi = conformal.interval
    assert lo <= 74_800.0 <= hi and conformal.status == "certified"
    assert conformal.labels == ("sunny", "light_rain")
    assert conformal.speed_command_mps <= safe_set.speed_command_mps


def test_the_conformal_block_falls_back_to_the_envelope_when_every_label_qualifies(designs):
    conditions = load_conditions()
    calibration = RobustConformalCalibration(thresholds={0: 0.0, 1: 0.0, 2: 0.0},
                                             frames_per_label={0: 0, 1: 0, 2: 0},
                                             num_classes=3, sigma=SIGMA, n=1000)
    p = result_with_votes([1000, 0, 0], true_label=0, stiffness=100_000.0)
    decision = CertifiedInterval(designs, conditions, PERCEPTION,
                                 inputs=IntervalInputs(conformal=calibration)).request(p)
    assert decision.status == "envelope"
    assert decision.interval == tuple(conditions.envelope(PRESET))
