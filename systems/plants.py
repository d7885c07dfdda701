"""Lateral vehicle plants with the same named ports (DESIGN section 2).

Input ports (each of size 1):
  ``steering_rad``         front steering angle u (rad, > 0 left), after the Saturation
  ``stiffness_n_per_rad``  true cornering stiffness C of ONE tire (N/rad)
  ``friction_mu``          tire-road friction coefficient mu (-); only the nonlinear plant uses it
  ``speed_mps``            forward speed V (m/s, >= 0), may vary in time; below the plant's
                           stop speed (default 5 m/s, DESIGN 2) the lateral dynamics are frozen
  ``curvature_per_m``      road curvature kappa (1/m, > 0 left turn)
Output port:
  ``state``  s = [e1, e1dot, e2, e2dot] (m, m/s, rad, rad/s): lateral offset from the lane
             centre (> 0 left) and heading error, Rajamani's error coordinates.

``LinearLateralPlant`` is eq. 2.45; ``NonlinearLateralPlant`` is the single track with
Fiala brush tires (saturating at mu F_z), exact slip kinematics and Frenet road coordinates.
Both are ``SymbolicVectorSystem``s behind a ``Multiplexer`` that names the ports, so their
derivatives are evaluated in C++. ``ExactDiscreteLinearPlant`` is the zero-order-hold
discretisation of eq. 2.45 at a sample period, for fixed (C, V).
"""

import dataclasses

import numpy as np
import pydrake.symbolic as sym
import scipy.linalg
from pydrake.systems.analysis import DiscreteTimeApproximation
from pydrake.systems.framework import Diagram, DiagramBuilder
from pydrake.systems.primitives import AffineSystem, Multiplexer, SymbolicVectorSystem

from drake_cert.config import GRAVITY_MPS2, VehicleParams
from drake_cert.dynamics import lateral_error_dynamics, yaw_rate_command
from drake_cert.errors import ConfigError
from drake_cert.systems import generic_math as gm

PLANT_INPUTS = ("steering_rad", "stiffness_n_per_rad", "friction_mu", "speed_mps",
                "curvature_per_m")
STOP_SPEED_MPS = 5.0  # below this forward speed the lateral dynamics are frozen (DESIGN 2)


@dataclasses.dataclass(frozen=True)
class PlantInputs:
    """The nonlinear plant's inputs (its ports, :data:`PLANT_INPUTS`); floats or symbolic."""

    steering: object  # front steering angle u (rad)
    stiffness: object  # cornering stiffness C per front tire (N/rad)
    friction_mu: object  # tire-road friction coefficient
    speed: object  # forward speed V (m/s)
    curvature: object  # road curvature kappa (1/m)


def frozen_below_stop_speed(derivatives_at, speed, stop_speed_mps: float):
    """Derivatives that are 0 below the stop speed, never dividing by a small V.

    ``derivatives_at(V_eff)`` builds the derivatives at ``V_eff = max(V, v_stop)`` (so the
    1/V terms stay finite at V = 0); each entry is then ``if V >= v_stop then it else 0``.
    At V >= v_stop this is the unfrozen expression evaluated at V exactly. Symbolic.
    """
    if not stop_speed_mps > 0:
        raise ConfigError(f"stop_speed_mps = {stop_speed_mps!r} must be positive")
    effective = sym.max(speed, float(stop_speed_mps))
    return np.array([gm.where(speed >= float(stop_speed_mps), d, sym.Expression(0.0))
                     for d in derivatives_at(effective)])


# --------------------------------------------------------------------------- equations

def linear_error_derivatives(vehicle: VehicleParams, s, steering, stiffness, speed, curvature):
    """``sdot = A(C,V) s + b(C) u + g(C,V) V kappa`` (Rajamani eq. 2.45), float or symbolic."""
    a, b, g = lateral_error_dynamics(vehicle, stiffness, speed)
    return (gm.matvec(a, s) + gm.scaled(b, steering)
            + gm.scaled(g, yaw_rate_command(speed, curvature)))


def static_tire_loads(vehicle: VehicleParams) -> tuple[float, float]:
    """Vertical load per tire (N), front and rear, from the static axle loads."""
    weight = vehicle.mass_kg * GRAVITY_MPS2
    wheelbase = vehicle.lf_m + vehicle.lr_m
    return (0.5 * weight * vehicle.lr_m / wheelbase, 0.5 * weight * vehicle.lf_m / wheelbase)


def fiala_lateral_force(slip_angle, stiffness, friction_mu, normal_load):
    """Fiala brush-tire lateral force of one tire (N) at slip angle a (rad, |a| < pi/2).

    ``F = -C tan a + C^2/(3 mu Fz) |tan a| tan a - C^3/(27 mu^2 Fz^2) tan^3 a`` for
    ``|tan a| < 3 mu Fz / C``, else ``-mu Fz sign(a)`` (full sliding). Slope -C at a = 0;
    continuous and monotone, |F| <= mu Fz. Float or symbolic.
    """
    return fiala_force_from_tan(gm.tan(slip_angle), stiffness, friction_mu, normal_load)


def fiala_force_from_tan(tan_slip, stiffness, friction_mu, normal_load):
    """:func:`fiala_lateral_force` in terms of ``tan a`` (the kinematics give tan a directly).

    With ``z = C tan a / (3 mu Fz)`` the brush model reads ``F = -mu Fz (3z - 3z|z| + z^3)``
    for ``|z| < 1`` and ``-mu Fz sign(z)`` beyond (fewer operations in the C++ expression).
    """
    mu_fz = friction_mu * normal_load
    z = stiffness * tan_slip / (3.0 * mu_fz)
    adhesion = -mu_fz * z * (3.0 - 3.0 * gm.absolute(z) + z * z)
    return gm.where(gm.absolute(z) < 1.0, adhesion, -mu_fz * gm.sign(z))


def single_track_derivatives(vehicle: VehicleParams, x, inputs: PlantInputs):
    """Time derivative of the body state ``x = [e1, vy, e2, r]`` of the nonlinear plant at
    ``inputs`` (:class:`PlantInputs`: steering u, stiffness C, friction mu, V, kappa).

    Single track at constant forward speed V (body frame), lateral velocity vy (m/s), yaw
    rate r (rad/s), Frenet offset e1 and heading error e2 to a road of curvature kappa.
    Slip angles from the exact kinematics, ``a_f = atan((vy + l_f r)/V) - u``,
    ``a_r = atan((vy - l_r r)/V)``; two Fiala tires per axle; the front force acts at the
    steering angle (its longitudinal part is taken up by the drive, V constant).
    ``e1dot = V sin e2 + vy cos e2``, ``e2dot = r - psidot_road`` with
    ``psidot_road = kappa (V cos e2 - vy sin e2) / (1 - kappa e1)``.
    """
    steering, stiffness, friction_mu = inputs.steering, inputs.stiffness, inputs.friction_mu
    speed, curvature = inputs.speed, inputs.curvature
    e1, vy, e2, r = x
    m, iz, lf, lr = vehicle.mass_kg, vehicle.yaw_inertia_kg_m2, vehicle.lf_m, vehicle.lr_m
    fz_f, fz_r = static_tire_loads(vehicle)
    # tan of the slip angles a_f = atan(q_f) - u and a_r = atan(q_r), without atan:
    # tan(atan(q) - u) = (q - tan u) / (1 + q tan u).
    q_f = (vy + lf * r) / speed
    tan_u = gm.tan(steering)
    tan_slip_f = (q_f - tan_u) / (1.0 + q_f * tan_u)
    tan_slip_r = (vy - lr * r) / speed
    f_f = 2.0 * fiala_force_from_tan(tan_slip_f, stiffness, friction_mu, fz_f)
    f_r = 2.0 * fiala_force_from_tan(tan_slip_r, vehicle.rear_stiffness_ratio * stiffness,
                                     friction_mu, fz_r)
    vy_dot = (f_f * gm.cos(steering) + f_r) / m - speed * r
    r_dot = (lf * f_f * gm.cos(steering) - lr * f_r) / iz
    return np.array([
        speed * gm.sin(e2) + vy * gm.cos(e2),
        vy_dot,
        r - road_yaw_rate(x, speed, curvature),
        r_dot,
    ])


def road_yaw_rate(x, speed, curvature):
    """Heading rate of the road at the car's projection (rad/s).

    ``kappa (V cos e2 - vy sin e2) / (1 - kappa e1)``: the projection's arc-length rate times kappa.
    """
    e1, vy, e2, _ = x
    return curvature * (speed * gm.cos(e2) - vy * gm.sin(e2)) / (1.0 - curvature * e1)


def error_state_from_body(x, speed, curvature):
    """Error coordinates ``s = [e1, e1dot, e2, e2dot]`` of the body state ``[e1, vy, e2, r]``."""
    e1, vy, e2, r = x
    return np.array([e1, speed * gm.sin(e2) + vy * gm.cos(e2), e2,
                     r - road_yaw_rate(x, speed, curvature)])


def body_state_from_error(s, speed, curvature):
    """Inverse of :func:`error_state_from_body`: ``[e1, vy, e2, r]`` from s (|e2| < pi/2)."""
    e1, e1dot, e2, e2dot = s
    vy = (e1dot - speed * gm.sin(e2)) / gm.cos(e2)
    r = e2dot + road_yaw_rate([e1, vy, e2, 0.0], speed, curvature)
    return np.array([e1, vy, e2, r])


def nonlinear_error_derivatives(vehicle: VehicleParams, s, inputs: PlantInputs):
    """``sdot`` of the nonlinear plant in error coordinates at constant curvature, at
    ``inputs`` (:class:`PlantInputs`).

    Chain rule of :func:`error_state_from_body` along :func:`single_track_derivatives`
    (kappa held constant, as eq. 2.45 does); used to compare the two plants. Float or symbolic.
    """
    speed, curvature = inputs.speed, inputs.curvature
    x = body_state_from_error(s, speed, curvature)
    e1, vy, e2, _ = x
    e1_dot, vy_dot, e2_dot, r_dot = single_track_derivatives(vehicle, x, inputs)
    along = speed * gm.cos(e2) - vy * gm.sin(e2)  # road-direction speed (m/s)
    along_dot = (-speed * gm.sin(e2) - vy * gm.cos(e2)) * e2_dot - gm.sin(e2) * vy_dot
    shrink = 1.0 - curvature * e1
    road_yaw_dot = curvature * (along_dot / shrink + along * curvature * e1_dot / shrink**2)
    return np.array([
        e1_dot,
        along * e2_dot + gm.cos(e2) * vy_dot,
        e2_dot,
        r_dot - road_yaw_dot,
    ])


# --------------------------------------------------------------------------- systems

class _NamedInputPlant(Diagram):
    """Exports each scalar input of a vector system under a name, and its output as "state"."""

    def _build(self, builder: DiagramBuilder, core, input_names, output_port) -> None:
        mux = builder.AddSystem(Multiplexer([1] * len(input_names)))
        builder.Connect(mux.get_output_port(0), core.get_input_port(0))
        for i, name in enumerate(input_names):
            builder.ExportInput(mux.get_input_port(i), name)
        builder.ExportOutput(output_port, "state")
        builder.BuildInto(self)


class LinearLateralPlant(_NamedInputPlant):
    """Rajamani eq. 2.45 as a continuous-time system (C++-evaluated); state = output = s.

    ``friction_mu`` is accepted (same ports as the nonlinear plant) and ignored. Below
    ``stop_speed_mps`` the state is frozen (sdot = 0; :func:`frozen_below_stop_speed`).
    """

    def __init__(self, vehicle: VehicleParams, stop_speed_mps: float = STOP_SPEED_MPS):
        super().__init__()
        s = sym.MakeVectorVariable(4, "s")
        u, c, mu, v, kappa = (sym.Variable(n) for n in PLANT_INPUTS)
        self.stop_speed_mps = float(stop_speed_mps)
        with np.errstate(invalid="ignore"):  # numpy flags object arithmetic spuriously
            dynamics = frozen_below_stop_speed(
                lambda v_eff: linear_error_derivatives(vehicle, s, u, c, v_eff, kappa), v,
                stop_speed_mps)
        builder = DiagramBuilder()
        core = builder.AddNamedSystem("eq_2_45", SymbolicVectorSystem(
            state=s, input=[u, c, mu, v, kappa], dynamics=dynamics, output=s))
        self._build(builder, core, PLANT_INPUTS, core.get_output_port(0))
        self.set_name("linear_lateral_plant")


def _single_track_system(vehicle: VehicleParams, stop_speed_mps: float) -> SymbolicVectorSystem:
    """The single track's state [e1, vy, e2, r] under the inputs :data:`PLANT_INPUTS`, frozen
    below the stop speed (:func:`frozen_below_stop_speed`)."""
    x = sym.MakeVectorVariable(4, "x")
    u, c, mu, v, kappa = (sym.Variable(n) for n in PLANT_INPUTS)
    with np.errstate(invalid="ignore"):  # numpy flags object-array arithmetic spuriously
        x_dot = frozen_below_stop_speed(
            lambda v_eff: single_track_derivatives(vehicle, x,
                                                   PlantInputs(u, c, mu, v_eff, kappa)), v,
            stop_speed_mps)
    return SymbolicVectorSystem(state=x, input=[u, c, mu, v, kappa], dynamics=x_dot, output=x)


def _error_coordinates_system() -> SymbolicVectorSystem:
    """The output map (x, V, kappa) -> s. Drake 1.51's SymbolicVectorSystem requires a state
    when it sits in a continuous diagram: it carries one constant dummy state (derivative 0)."""
    xin = sym.MakeVectorVariable(4, "x_in")
    v_in, kappa_in = sym.Variable("speed"), sym.Variable("curvature")
    return SymbolicVectorSystem(
        state=[sym.Variable("unused")], input=np.concatenate([xin, [v_in, kappa_in]]),
        dynamics=[sym.Expression(0.0)], output=error_state_from_body(xin, v_in, kappa_in))


class NonlinearLateralPlant(_NamedInputPlant):
    """Single track with Fiala tires; continuous state ``[e1, vy, e2, r]``, output s.

    The output s depends on ``curvature_per_m`` directly (e2dot = r - road yaw rate), not on
    ``steering_rad``, so a state-feedback controller closes no algebraic loop.
    The speed input may vary in time (the lateral equations hold for a varying forward
    speed); below ``stop_speed_mps`` the body state is frozen (:func:`frozen_below_stop_speed`),
    and the output map, which has no 1/V, still uses the actual V.
    """

    def __init__(self, vehicle: VehicleParams, stop_speed_mps: float = STOP_SPEED_MPS):
        super().__init__()
        self.stop_speed_mps = float(stop_speed_mps)
        builder = DiagramBuilder()
        dynamics = builder.AddNamedSystem("single_track",
                                          _single_track_system(vehicle, self.stop_speed_mps))
        to_error = builder.AddNamedSystem("error_coordinates", _error_coordinates_system())
        # (x, V, kappa) -> s; V and kappa come from the exported inputs' multiplexer.
        mux = builder.AddSystem(Multiplexer([1] * len(PLANT_INPUTS)))
        builder.Connect(mux.get_output_port(0), dynamics.get_input_port(0))
        out_mux = builder.AddSystem(Multiplexer([4, 1, 1]))
        builder.Connect(dynamics.get_output_port(0), out_mux.get_input_port(0))
        builder.Connect(out_mux.get_output_port(0), to_error.get_input_port(0))
        for i, name in enumerate(PLANT_INPUTS):
            builder.ExportInput(mux.get_input_port(i), name)
        # A second route of the speed and curvature inputs into the output map.
        builder.ConnectInput("speed_mps", out_mux.get_input_port(1))
        builder.ConnectInput("curvature_per_m", out_mux.get_input_port(2))
        builder.ExportOutput(to_error.get_output_port(0), "state")
        builder.BuildInto(self)
        self.set_name("nonlinear_lateral_plant")
        self._dynamics = dynamics

    def body_state_subsystem(self):
        """The SymbolicVectorSystem holding the continuous body state ``[e1, vy, e2, r]``."""
        return self._dynamics


def exact_discretisation(vehicle: VehicleParams, stiffness, speed, period):
    """ZOH discretisation of eq. 2.45: ``s[k+1] = Ad s[k] + Bd [u[k], kappa[k]]``, exact.

    From one matrix exponential of the augmented ``[[A, b, g V], [0, 0, 0]]`` (an
    independent check of Drake's ``DiscreteTimeApproximation`` used by the plant below).
    """
    a, b, g = lateral_error_dynamics(vehicle, float(stiffness), float(speed))
    m = np.zeros((6, 6))
    m[:4, :4] = a
    m[:4, 4] = b
    m[:4, 5] = g * speed  # psidot_des = V kappa
    e = scipy.linalg.expm(m * period)
    return e[:4, :4], e[:4, 4:]


class ExactDiscreteLinearPlant(Diagram):
    """Eq. 2.45 sampled with zero-order hold at ``period_s`` for fixed (C, V): exact
    (Drake's ``DiscreteTimeApproximation`` of the continuous affine system).

    Inputs ``steering_rad`` and ``curvature_per_m`` only (C and V are construction
    parameters of a constant-parameter episode); output ``state`` = s[k]. Steering and
    curvature are read at the sample instants and held for one period.
    """

    def __init__(self, vehicle: VehicleParams, stiffness_n_per_rad: float, speed_mps: float,
                 period_s: float):
        super().__init__()
        a, b, g = lateral_error_dynamics(vehicle, float(stiffness_n_per_rad), float(speed_mps))
        continuous = AffineSystem(A=a, B=np.column_stack([b, g * speed_mps]), f0=np.zeros(4),
                                  C=np.eye(4), D=np.zeros((4, 2)), y0=np.zeros(4))
        builder = DiagramBuilder()
        core = builder.AddNamedSystem("eq_2_45_zoh",
                                      DiscreteTimeApproximation(continuous, period_s))
        mux = builder.AddSystem(Multiplexer([1, 1]))
        builder.Connect(mux.get_output_port(0), core.get_input_port(0))
        builder.ExportInput(mux.get_input_port(0), "steering_rad")
        builder.ExportInput(mux.get_input_port(1), "curvature_per_m")
        builder.ExportOutput(core.get_output_port(0), "state")
        builder.BuildInto(self)
        self.set_name("exact_discrete_linear_plant")
