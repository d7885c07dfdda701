"""One failure probability for a whole drive (DESIGN 6.2): the alphas a drive's decisions are
taken at sum to at most its total, however many decisions it takes, and the drive reports the
union bound it spent."""

import dataclasses
import math

import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from drake_cert.certification.alpha_spending import AlphaSpending, planned_decisions
from drake_cert.config import load_conditions
from drake_cert.errors import CertificationError
from drake_cert.perception.models import load_model
from drake_cert.systems.camera import CameraFrame
from drake_cert.systems.driving import alpha_spending, certificate_failure_bound
from drake_cert.systems.perception_smoothing import PerceptionInputs, PerceptionSmoothing
from drake_cert.systems.scenario import PerceptionSettings, load_scenario


@given(total=st.floats(1e-6, 0.5), planned=st.integers(1, 2000),
       ticks=st.integers(0, 20000))
def test_the_alphas_of_any_number_of_decisions_sum_to_at_most_the_total(total, planned, ticks):
    spending = AlphaSpending(total, planned)
    assert spending.spent(ticks) <= total * (1 + 1e-12)
    assert spending.spent(ticks) == pytest.approx(
        math.fsum(spending.alpha(k) for k in range(ticks)), rel=1e-9, abs=1e-300)


def test_planned_ticks_share_nine_tenths_evenly_and_later_ones_a_shrinking_tail():
    s = AlphaSpending(0.01, 300)
    assert s.alpha(0) == s.alpha(299) == pytest.approx(0.9 * 0.01 / 300)
    tail = [s.alpha(300 + j) for j in range(5)]
    assert tail[0] == pytest.approx(0.1 * 0.01 / 2)
    assert all(a > b for a, b in zip(tail[:-1], tail[1:], strict=True))
    assert s.spent(300) == pytest.approx(0.009)
    assert s.spent(10**9) == pytest.approx(0.01, rel=1e-6)


def test_bad_totals_and_plans_are_refused():
    with pytest.raises(CertificationError):
        AlphaSpending(0.0, 10)
    with pytest.raises(CertificationError):
        AlphaSpending(0.01, 0)
    with pytest.raises(ValueError):
        AlphaSpending(0.01, 10).alpha(-1)


def test_the_plan_is_the_route_and_lead_in_at_the_slowest_moving_speed():
    assert planned_decisions(380.0, 6.2, 5.0) == math.ceil(5.0 * 380.0 / 6.2) + 1
    assert planned_decisions(380.0, 6.2, 5.0, duration_s=3.0) == 16  # a drive cut by time


def test_each_tick_of_the_perception_block_decides_at_its_own_alpha():
    conditions = load_conditions()
    labels = tuple(conditions.preset("robotcar-like").labels)
    spending = AlphaSpending(0.01, 3)
    settings = PerceptionSettings(sigma=0.25, n0=0, n=200, batch_size=200, eps=0.1,
                                  decision="sequential")
    block = PerceptionSmoothing(load_model("robotcar-like", "classify", 0.25), settings,
                                inputs=PerceptionInputs(
                                    label_names=labels,
                                    ranges=[(0,), (1,), (2,), (0, 1), (1, 2)],
                                    alpha_spending=spending))
    image = torch.full((3, 64, 64), 0.5)
    for tick in (0, 2, 3, 7):
        frame = CameraFrame(image=image, time_s=0.2 * tick, tick=tick, position_m=0.0,
                            label_index=0, stiffness_n_per_rad=1e5, friction_mu=0.9)
        result = block.perceive(frame, 0.2 * tick)
        assert result.decision is not None
        assert result.decision.alpha == pytest.approx(spending.alpha(tick))


def test_a_shipped_drive_spends_its_alpha_over_the_plan_and_reports_the_bound():
    scenario = load_scenario("dry_to_snow")
    assert scenario.perception.alpha_scope == "drive"

    class Design:  # only the speeds matter to the plan
        def __init__(self, speed):
            self.speed_mps, self.has_safe_speed = speed, True

    table = [Design(19.4), Design(16.0), Design(6.2)]
    spending = alpha_spending(scenario, table)
    distance = scenario.route_length_m + scenario.camera.look_ahead_m
    assert spending.planned == planned_decisions(distance, 6.2, scenario.camera.rate_hz)
    assert spending.total == scenario.perception.alpha
    assert certificate_failure_bound(scenario, spending, 10**6) <= scenario.perception.alpha
    per_decision = dataclasses.replace(scenario, perception=dataclasses.replace(
        scenario.perception, alpha_scope="decision", alpha=0.001))
    assert alpha_spending(per_decision, table) is None
    assert certificate_failure_bound(per_decision, None, 170) == pytest.approx(0.17)
    base = dataclasses.replace(scenario, perception=dataclasses.replace(
        scenario.perception, pipeline="base"))
    assert alpha_spending(base, table) is None
    assert certificate_failure_bound(base, None, 170) == 0.0
