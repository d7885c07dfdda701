"""The grip condition (DESIGN 5.3d) is tight on the Fiala plant: certified >= 90% of the limit."""

import numpy as np

from drake_cert import metrics
from drake_cert.config import GRAVITY_MPS2, load_conditions, load_settings, load_vehicle
from drake_cert.synthesis.table import synthesize_design
from drake_cert.systems.closed_loop import EpisodeOptions, simulate
from drake_cert.systems.road import Road

CAR, SETTINGS = load_vehicle(), load_settings()


def _in_lane(design, stiffness, mu, speed, road):
    tape = simulate(vehicle=CAR, design=design, settings=SETTINGS, stiffness_n_per_rad=stiffness,
                    friction_mu=mu, speed_mps=speed, road=road,
                    episode=EpisodeOptions(plant="nonlinear",
                                           t_final_s=(road.knots_m[-1] + 100.0) / speed))
    return not tape.stopped_early and not metrics.left_lane(tape)


def test_heavy_rain_speed_is_within_90_percent_of_the_in_lane_limit_and_stays_in_lane():
    # The in-lane limit on the Fiala plant is a cliff near sqrt(mu g R) (DESIGN 5.3d): in lane at
    # the certified speed and out of it at certified / 0.9 puts the limit below certified / 0.9.
    cond = load_conditions().condition("heavy_rain")
    radius = SETTINGS.synthesis.design_radius_m
    d = synthesize_design(CAR, cond.interval, cond.friction_mu, SETTINGS, ["heavy_rain"])
    assert d.speed_mps >= 0.9 * np.sqrt(cond.friction_mu * GRAVITY_MPS2 * radius)
    road = Road.curve(radius_m=radius)
    lo = cond.stiffness_lo_n_per_rad
    assert _in_lane(d, lo, cond.friction_mu, d.speed_mps, road)
    assert not _in_lane(d, lo, cond.friction_mu, d.speed_mps / 0.9, road)
    # and at the certified speed with the other stiffnesses of the label and a curvature step
    step = Road((0.0, 40.0, 40.001), (0.0, 0.0, 1.0 / radius))
    for stiffness in (0.5 * (lo + cond.stiffness_hi_n_per_rad), cond.stiffness_hi_n_per_rad):
        assert _in_lane(d, stiffness, cond.friction_mu, d.speed_mps, road), stiffness
    assert _in_lane(d, lo, cond.friction_mu, d.speed_mps, step)
