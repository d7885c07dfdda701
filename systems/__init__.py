"""Drake systems: lateral plants, the L1 adaptive controller, the road, the closed-loop diagram.

Main entry points: :class:`systems.plants.LinearLateralPlant`,
:class:`systems.plants.NonlinearLateralPlant`, :class:`systems.l1_controller.L1AdaptiveController`,
:class:`systems.road.Road` and :func:`systems.closed_loop.simulate` (returns a
:class:`systems.closed_loop.Tape`).
"""

from systems.closed_loop import ClosedLoop, Tape, build_closed_loop, simulate
from systems.l1_controller import L1AdaptiveController
from systems.plants import ExactDiscreteLinearPlant, LinearLateralPlant, NonlinearLateralPlant
from systems.road import Road

__all__ = ["ClosedLoop", "ExactDiscreteLinearPlant", "L1AdaptiveController",
           "LinearLateralPlant", "NonlinearLateralPlant", "Road", "Tape", "build_closed_loop",
           "simulate"]
