"""Closed-loop episodes of the per-frame experiments (DESIGN 7).

An episode drives the car with one design at that design's safe speed on the Fiala
evaluation plant, with the frame's TRUE stiffness and friction, over the design road (a
curve of the design radius placed in ``duration_s`` of driving), and reports whether it left
its lane. A speed of 0 is a stop: no episode, never unstable. Outcomes depend only on
(design, speed, stiffness, friction), so they are cached by exactly that key.
"""

from __future__ import annotations

import dataclasses

from drake_cert import metrics
from drake_cert.config import Settings, VehicleParams
from drake_cert.synthesis.design import ControllerDesign
from drake_cert.systems.closed_loop import EpisodeOptions, simulate
from drake_cert.systems.road import Road

EPISODE_S = 20.0  # simulated seconds per episode


@dataclasses.dataclass(frozen=True)
class EpisodeOutcome:
    left_lane: bool
    peak_abs_e1_m: float
    speed_mps: float


class EpisodeRunner:
    """Runs (and caches) episodes for one vehicle and settings."""

    def __init__(self, vehicle: VehicleParams, settings: Settings, duration_s: float = EPISODE_S):
        self.vehicle, self.settings, self.duration_s = vehicle, settings, duration_s
        self._cache: dict[tuple, EpisodeOutcome] = {}
        self.simulated = 0

    def outcome(self, design: ControllerDesign, stiffness_n_per_rad: float,
                friction_mu: float) -> EpisodeOutcome:
        """Drive ``design`` at its safe speed; a design without one stops the car."""
        speed = float(design.speed_mps) if design.has_safe_speed else 0.0
        if speed <= 0.0:
            return EpisodeOutcome(False, 0.0, 0.0)
        key = (tuple(design.labels), design.interval, tuple(design.k_m), design.filter_gain, speed,
               float(stiffness_n_per_rad), float(friction_mu))
        if key not in self._cache:
            tape = self.tape(design, stiffness_n_per_rad, friction_mu)
            self._cache[key] = EpisodeOutcome(metrics.left_lane(tape),
                                              metrics.peak_lateral_offset(tape), speed)
            self.simulated += 1
        return self._cache[key]

    def tape(self, design: ControllerDesign, stiffness_n_per_rad: float, friction_mu: float):
        """The logged episode (not cached) of ``design`` at its safe speed, which must be > 0."""
        speed = float(design.speed_mps)
        road = Road.episode_curve(radius_m=self.settings.synthesis.design_radius_m,
                                  length_m=speed * self.duration_s)
        return simulate(vehicle=self.vehicle, design=design, settings=self.settings,
                        stiffness_n_per_rad=float(stiffness_n_per_rad),
                        friction_mu=float(friction_mu), speed_mps=speed, road=road,
                        episode=EpisodeOptions(plant="nonlinear", t_final_s=self.duration_s,
                                               tape_period_s=0.05))
