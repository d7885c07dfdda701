"""The closed-loop diagram (plant + L1 controller + Saturation + logs) and ``simulate``.

    road curvature (TrajectorySource) --+--> controller --> Saturation --> plant --> state
    C, mu, V (ConstantVectorSource) ----|------------------------------->   |          |
                                        +------------------------------->   |          |
                                        state <------------------------------------------+
With ``settings.controller.preview_window_s > 0`` a second TrajectorySource feeds the
controller the road preview, the mean curvature ahead (``Road.preview_curvature_trajectory``;
the curvature feedforward is taken at it, see :mod:`drake_cert.systems.l1_law`).
Loggers (``LogVectorOutput``, one sample per tape period) record the plant state, the
saturated steering and the curvature. ``simulate`` builds the diagram, sets the initial
state, advances and returns a :class:`Tape` (Drake tutorial style). A simulator monitor
(``Simulator.set_monitor``) ends an episode once the car is off the road (|e1| > ``OFF_ROAD_M``).
"""

import dataclasses

import numpy as np
from pydrake.systems.analysis import (
    ApplySimulatorConfig,
    Simulator,
    SimulatorConfig,
    SimulatorStatus,
)
from pydrake.systems.framework import Diagram, DiagramBuilder, EventStatus
from pydrake.systems.primitives import (
    ConstantVectorSource,
    LogVectorOutput,
    Saturation,
    TrajectorySource,
)

from drake_cert import metrics
from drake_cert.config import Settings, VehicleParams
from drake_cert.errors import ConfigError
from drake_cert.synthesis.design import ControllerDesign
from drake_cert.systems.l1_controller import L1AdaptiveController
from drake_cert.systems.l1_law import L1Options
from drake_cert.systems.l1_reference import L1AdaptiveControllerReference
from drake_cert.systems.plants import (
    ExactDiscreteLinearPlant,
    LinearLateralPlant,
    NonlinearLateralPlant,
    body_state_from_error,
)
from drake_cert.systems.road import Road

PLANTS = ("nonlinear", "linear", "linear_sampled")
OFF_ROAD_M = 5.0  # |e1| (m) at which an episode stops: the car has left its lane for good


@dataclasses.dataclass
class Tape:
    """Logged closed-loop signals of one episode, sampled every tape period."""

    times_s: np.ndarray  # (N,) s
    states: np.ndarray  # (N, 4) s = [e1 (m), e1dot (m/s), e2 (rad), e2dot (rad/s)]
    steering_rad: np.ndarray  # (N,) applied (saturated) steering
    curvature_per_m: np.ndarray  # (N,) road curvature
    lane_margin_m: float  # |e1| beyond which the car has left its lane
    speed_mps: float
    stiffness_n_per_rad: float  # true C per tire
    friction_mu: float
    plant: str
    law: str
    simulated_s: float = float("nan")  # simulated time at the end of the episode (s)
    stopped_early: bool = False  # True when the off-road monitor ended the episode

    @property
    def lateral_offset_m(self) -> np.ndarray:
        """e1(t) (m), > 0 left of the lane centre."""
        return self.states[:, 0]

    @property
    def time_left_lane_s(self) -> float | None:
        """First time |e1| exceeded the lane margin (s), interpolated linearly between tape
        samples; None if the car stayed in its lane (see :func:`metrics.time_left_lane`)."""
        return metrics.time_left_lane(self)


@dataclasses.dataclass(frozen=True)
class TrueCondition:
    """The true road and speed of one episode (what the plant sees, not what was designed)."""

    stiffness_n_per_rad: float  # true cornering stiffness C per tire (N/rad)
    friction_mu: float  # true tire-road friction coefficient
    speed_mps: float  # constant forward speed V (m/s)


@dataclasses.dataclass(frozen=True)
class EpisodeOptions:
    """How one closed-loop episode is built and run (:func:`build_closed_loop`,
    :func:`simulate`)."""

    plant: str = "nonlinear"  # "nonlinear", "linear" or "linear_sampled" (PLANTS)
    law: str | None = None  # adaptation law; None: settings.controller.adaptation_law
    t_final_s: float = 20.0  # episode length (s)
    tape_period_s: float = 0.01  # logging period (s)
    initial_state: object = None  # s(0) = [e1, e1dot, e2, e2dot]; None: zeros (simulate only)
    config: SimulatorConfig | None = None  # overrides simulator_config (simulate only)
    reference_controller: bool = False  # the Python reference controller instead of C++


@dataclasses.dataclass
class ClosedLoop:
    """The built diagram and the handles ``simulate`` needs."""

    diagram: Diagram
    plant: object
    controller: L1AdaptiveController
    loggers: dict  # name -> VectorLogSink
    plant_kind: str


def build_closed_loop(*, vehicle: VehicleParams, design: ControllerDesign, settings: Settings,
                      condition: TrueCondition, road: Road,
                      episode: EpisodeOptions | None = None) -> ClosedLoop:
    """Wire road source, L1 controller, Saturation, plant and loggers into one Diagram.

    ``condition``: the true stiffness, friction and speed (:class:`TrueCondition`).
    ``episode`` (:class:`EpisodeOptions`; its initial_state and config are :func:`simulate`'s):
    ``plant`` "nonlinear" (Fiala single track), "linear" (eq. 2.45, continuous) or
    "linear_sampled" (eq. 2.45 discretised exactly with the steering held over T_s; for the
    piecewise-constant law only, whose updates happen at the same instants);
    ``reference_controller`` uses the Python LeafSystem of the same equations
    (:class:`drake_cert.systems.l1_reference.L1AdaptiveControllerReference`) instead of the C++ one.
    """
    episode = episode or EpisodeOptions()
    stiffness_n_per_rad, friction_mu = condition.stiffness_n_per_rad, condition.friction_mu
    speed_mps, plant = condition.speed_mps, episode.plant
    t_final_s, tape_period_s = episode.t_final_s, episode.tape_period_s
    law = episode.law or settings.controller.adaptation_law
    if plant not in PLANTS:
        raise ConfigError(f"unknown plant {plant!r}; expected one of {PLANTS}")
    if plant == "linear_sampled" and law != "piecewise_constant":
        raise ConfigError("plant 'linear_sampled' needs law 'piecewise_constant' "
                          f"(got {law!r})")
    for name, value in (("stiffness_n_per_rad", stiffness_n_per_rad),
                        ("friction_mu", friction_mu), ("speed_mps", speed_mps),
                        ("t_final_s", t_final_s), ("tape_period_s", tape_period_s)):
        if not (np.isfinite(value) and value > 0):
            raise ConfigError(f"{name} = {value!r} must be a positive finite number")
    builder = DiagramBuilder()
    controller_class = L1AdaptiveControllerReference if episode.reference_controller else \
        L1AdaptiveController
    ctl = settings.controller
    preview = ctl.preview_window_s > 0
    controller = builder.AddSystem(controller_class(
        vehicle=vehicle, design=design, settings=settings, speed_mps=speed_mps,
        options=L1Options(
            law=law, curvature_preview=preview,
            e2dot_from_yaw_rate=plant == "nonlinear")))  # eq. 2.45's e2dot does not jump
    if plant == "nonlinear":
        plant_sys = builder.AddSystem(NonlinearLateralPlant(vehicle))
    elif plant == "linear":
        plant_sys = builder.AddSystem(LinearLateralPlant(vehicle))
    else:
        plant_sys = builder.AddSystem(ExactDiscreteLinearPlant(
            vehicle, stiffness_n_per_rad, speed_mps, settings.controller.sample_period_s))
    limit = vehicle.steering_limit_rad
    saturation = builder.AddNamedSystem("steering_saturation", Saturation([-limit], [limit]))
    curvature = builder.AddNamedSystem("road_curvature", TrajectorySource(
        road.curvature_trajectory(speed_mps, t_final_s)))
    builder.Connect(curvature.get_output_port(), controller.GetInputPort("curvature_per_m"))
    builder.Connect(curvature.get_output_port(), plant_sys.GetInputPort("curvature_per_m"))
    if preview:
        ahead = builder.AddNamedSystem("road_preview_curvature", TrajectorySource(
            road.preview_curvature_trajectory(speed_mps, t_final_s, ahead_s=ctl.preview_ahead_s,
                                              window_s=ctl.preview_window_s)))
        builder.Connect(ahead.get_output_port(),
                        controller.GetInputPort("curvature_preview_per_m"))
    builder.Connect(plant_sys.GetOutputPort("state"), controller.GetInputPort("state"))
    builder.Connect(controller.GetOutputPort("steering_rad"), saturation.get_input_port())
    builder.Connect(saturation.get_output_port(), plant_sys.GetInputPort("steering_rad"))
    if plant != "linear_sampled":
        for port, value in (("stiffness_n_per_rad", stiffness_n_per_rad),
                            ("friction_mu", friction_mu), ("speed_mps", speed_mps)):
            src = builder.AddNamedSystem(port, ConstantVectorSource([float(value)]))
            builder.Connect(src.get_output_port(), plant_sys.GetInputPort(port))
    loggers = {
        "state": LogVectorOutput(plant_sys.GetOutputPort("state"), builder, tape_period_s),
        "steering": LogVectorOutput(saturation.get_output_port(), builder, tape_period_s),
        "curvature": LogVectorOutput(curvature.get_output_port(), builder, tape_period_s),
    }
    diagram = builder.Build()
    diagram.set_name("lateral_closed_loop")
    return ClosedLoop(diagram, plant_sys, controller, loggers, plant)


def simulator_config(settings: Settings, law: str) -> SimulatorConfig:
    """Integrator settings used by :func:`simulate` for each law.

    Piecewise-constant law: its updates bound every step to T_s, so a fixed-step RK2 at T_s.
    Gradient law (stiff at Gamma = 1e4; explicit RK3 needs ~30x more wall time): the
    implicit, error-controlled Radau3 at accuracy 1e-4 (peak |e1| equal to 1e-6 to 4 digits),
    steps <= 10 ms.
    """
    cfg = SimulatorConfig()
    cfg.target_realtime_rate = 0.0
    cfg.publish_every_time_step = False
    if law == "piecewise_constant":
        cfg.integration_scheme = "runge_kutta2"
        cfg.use_error_control = False
        cfg.max_step_size = settings.controller.sample_period_s
    else:
        cfg.integration_scheme = "radau3"
        cfg.use_error_control = True
        cfg.accuracy = 1e-4
        cfg.max_step_size = 0.01
    return cfg


def simulate(*, vehicle: VehicleParams, design: ControllerDesign, settings: Settings,
             stiffness_n_per_rad: float, friction_mu: float, speed_mps: float, road: Road,
             episode: EpisodeOptions | None = None) -> Tape:
    """Simulate the closed loop for ``episode.t_final_s`` and return the logged :class:`Tape`.

    The true condition: ``stiffness_n_per_rad`` (C per tire, N/rad), ``friction_mu``,
    ``speed_mps`` (V, m/s). ``episode`` (:class:`EpisodeOptions`, default: its defaults):
    plant, law, t_final_s, tape_period_s (see :func:`build_closed_loop`) and
    ``initial_state``, s(0) = [e1, e1dot, e2, e2dot] (default zeros: on the lane centre);
    the controller's predictor starts at s(0). ``episode.config`` overrides
    :func:`simulator_config`.
    The episode ends early once |e1| > ``OFF_ROAD_M`` (a simulator monitor checks after every
    integration step and returns ``EventStatus.ReachedTermination``): the car has then left
    its lane, and the road frame (Frenet coordinates about a curve of radius R) stops making
    sense as |e1| approaches R. The tape then ends at the last tape sample before the stop,
    ``tape.stopped_early`` is True and ``tape.simulated_s`` is the time of the stop; its peak
    |e1| is the peak up to the stop (about ``OFF_ROAD_M``), so report
    ``tape.time_left_lane_s`` for such a run. Raises :class:`ConfigError` for an
    ``initial_state`` that is not 4 finite numbers.
    """
    episode = episode or EpisodeOptions()
    law = episode.law or settings.controller.adaptation_law
    episode = dataclasses.replace(episode, law=law)
    condition = TrueCondition(stiffness_n_per_rad, friction_mu, speed_mps)
    s0 = initial_error_state(episode.initial_state)
    loop = build_closed_loop(vehicle=vehicle, design=design, settings=settings,
                             condition=condition, road=road, episode=episode)
    simulator = Simulator(loop.diagram)
    ApplySimulatorConfig(episode.config or simulator_config(settings, law), simulator)
    context = simulator.get_mutable_context()
    kappa0 = float(road.curvature_at(0.0))
    set_plant_state(loop, context, s0, speed_mps, kappa0)
    loop.controller.set_initial_state(context, s0, kappa0)
    simulator.set_monitor(off_road_monitor(loop))
    simulator.Initialize()
    status = simulator.AdvanceTo(episode.t_final_s)
    stopped = status.reason() == SimulatorStatus.ReturnReason.kReachedTerminationCondition
    tape = tape_from_loggers(loop, context, vehicle=vehicle, condition=condition, law=law)
    tape.simulated_s = float(context.get_time())
    tape.stopped_early = bool(stopped)
    return tape


def initial_error_state(initial_state) -> np.ndarray:
    """s(0) as a float array of shape (4,) (zeros for None); ConfigError for anything else."""
    if initial_state is None:
        return np.zeros(4)
    try:
        s0 = np.asarray(initial_state, dtype=float)
    except (TypeError, ValueError):
        raise ConfigError(f"initial_state = {initial_state!r} must be 4 numbers "
                          "[e1 (m), e1dot (m/s), e2 (rad), e2dot (rad/s)]") from None
    if s0.shape != (4,) or not np.all(np.isfinite(s0)):
        raise ConfigError(f"initial_state = {initial_state!r} (shape {s0.shape}) must be 4 "
                          "finite numbers [e1 (m), e1dot (m/s), e2 (rad), e2dot (rad/s)]")
    return s0


def off_road_monitor(loop: ClosedLoop):
    """A ``Simulator`` monitor that ends the episode once |e1| > ``OFF_ROAD_M``."""
    state_port = loop.plant.GetOutputPort("state")

    def monitor(root_context):
        e1 = state_port.Eval(loop.plant.GetMyContextFromRoot(root_context))[0]
        if not abs(e1) <= OFF_ROAD_M:  # NaN too: a diverged simulation is off the road
            return EventStatus.ReachedTermination(
                loop.diagram, f"off the road: |e1| = {abs(e1):.2f} m > {OFF_ROAD_M} m")
        return EventStatus.Succeeded()

    return monitor


def set_plant_state(loop: ClosedLoop, context, s0, speed_mps: float, curvature: float) -> None:
    """Write the initial error state s0 into the plant's context (body state if nonlinear)."""
    plant_context = loop.plant.GetMyMutableContextFromRoot(context)
    if loop.plant_kind == "linear_sampled":
        plant_context.SetDiscreteState(np.asarray(s0, float))
    elif loop.plant_kind == "linear":
        plant_context.SetContinuousState(np.asarray(s0, float))
    else:
        core = loop.plant.body_state_subsystem()
        core.GetMyMutableContextFromRoot(context).SetContinuousState(
            np.asarray(body_state_from_error(s0, speed_mps, curvature), float))


def tape_from_loggers(loop: ClosedLoop, context, *, vehicle: VehicleParams,
                      condition: TrueCondition, law: str) -> Tape:
    """Collect the three logs into a :class:`Tape` (samples aligned by construction)."""
    speed_mps, friction_mu = condition.speed_mps, condition.friction_mu
    stiffness_n_per_rad = condition.stiffness_n_per_rad
    logs = {k: v.FindLog(context) for k, v in loop.loggers.items()}
    n = min(log.num_samples() for log in logs.values())
    return Tape(
        times_s=logs["state"].sample_times()[:n].copy(),
        states=logs["state"].data()[:, :n].T.copy(),
        steering_rad=logs["steering"].data()[0, :n].copy(),
        curvature_per_m=logs["curvature"].data()[0, :n].copy(),
        lane_margin_m=vehicle.lane_margin_m, speed_mps=float(speed_mps),
        stiffness_n_per_rad=float(stiffness_n_per_rad), friction_mu=float(friction_mu),
        plant=loop.plant_kind, law=law)
