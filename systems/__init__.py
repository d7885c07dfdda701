"""Drake systems: lateral plants, the L1 adaptive controller, the road, the closed-loop diagram.

Main entry points: :class:`drake_cert.systems.plants.LinearLateralPlant`,
:class:`drake_cert.systems.plants.NonlinearLateralPlant`,
:class:`drake_cert.systems.l1_controller.L1AdaptiveController`,
:class:`drake_cert.systems.road.Road` and :func:`drake_cert.systems.closed_loop.simulate` (returns a
:class:`drake_cert.systems.closed_loop.Tape`).
"""

from drake_cert.systems.closed_loop import (
    ClosedLoop,
    EpisodeOptions,
    Tape,
    TrueCondition,
    build_closed_loop,
    simulate,
)
from drake_cert.systems.l1_controller import L1AdaptiveController
from drake_cert.systems.plants import (
           ExactDiscreteLinearPlant,
           LinearLateralPlant,
           NonlinearLateralPlant,
)
from drake_cert.systems.road import Road

__all__ = ["ClosedLoop", "EpisodeOptions", "ExactDiscreteLinearPlant", "L1AdaptiveController",
           "LinearLateralPlant", "NonlinearLateralPlant", "Road", "Tape", "TrueCondition",
           "build_closed_loop", "simulate"]
