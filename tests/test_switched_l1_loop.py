"""The whole L1 loop under the worst switching we can construct (docs/design.md 5.6 (b)).

Claims, with the jointly synthesized robotcar-like designs, switching every camera frame (0.1 s)
between the two designs whose L1 loops differ most, at the slower one's safe speed and a
stiffness both hold:
- on the design model (``LinearLateralPlant``) the loop's state ``zeta = [s, u - u_ff]`` keeps
  ``zeta' P_z zeta <= e^(-2 lambda_z t) zeta(0)' P_z zeta(0)``, with ``P_z, lambda_z`` the
  family's loop certificate: no switch costs anything, so no dwell is needed;
- on the nonlinear plant (Fiala tires) the steering is continuous at every switch and the
  estimate the new design applies is as close to the new design's true uncertainty as the
  estimates between switches are to theirs (nothing drops out), and the car settles in lane,
  on a straight road from a 0.5 m offset and on the design radius.
The runs are the real switching controller (piecewise-constant law, T_s = 1 ms).
"""

import itertools

import numpy as np
import pytest
from pydrake.systems.analysis import ApplySimulatorConfig, Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import (
    ConstantVectorSource,
    LogVectorOutput,
    Saturation,
    TrajectorySource,
)
from pydrake.trajectories import PiecewisePolynomial

from drake_cert.synthesis.conditions import reference_system_matrix
from drake_cert.synthesis.loop_switching import steering_coordinates
from drake_cert.synthesis.switching import common_lyapunov_certificate, switching_families
from drake_cert.systems import l1_law
from drake_cert.systems.closed_loop import simulator_config
from drake_cert.systems.plants import (
    LinearLateralPlant,
    NonlinearLateralPlant,
    PlantInputs,
    body_state_from_error,
    nonlinear_error_derivatives,
)
from drake_cert.systems.switching_controller import (
    DESIGN,
    GRID,
    S_HAT,
    U_AD,
    SwitchingL1Controller,
    SwitchingOptions,
)

FRAME_S = 0.1  # a switch every camera frame (10 Hz)
DURATION_S = 8.0
S0 = np.array([0.5, 0.0, 0.0, 0.0])  # m, m/s, rad, rad/s


@pytest.fixture(scope="module")
def family(default_design_table):
    """The table, robotcar-like's designs with a safe speed and their switching certificate
    (as synthesize writes it for that preset)."""
    table = default_design_table
    designs = dict(switching_families(table.designs, table.conditions))["robotcar-like"]
    certificate = common_lyapunov_certificate(table.vehicle, designs, table.settings,
                                              "robotcar-like")
    return table, [d for d in designs if d.has_safe_speed], certificate


def loop_matrix(vehicle, design, stiffness, speed, law):
    return steering_coordinates(reference_system_matrix(
        vehicle, design.k_m, design.nominal_stiffness_n_per_rad, stiffness, speed,
        design.filter_gain, law), design.k_m)


def worst_pair(vehicle, designs, law):
    """The two designs with overlapping label intervals whose loop matrices (on zeta) differ
    most, at an end of the overlap, at the slower design's safe speed; returns (a, b, C, V)."""
    best = None
    for a, b in itertools.combinations(designs, 2):
        lo = max(a.stiffness_lo_n_per_rad, b.stiffness_lo_n_per_rad)
        hi = min(a.stiffness_hi_n_per_rad, b.stiffness_hi_n_per_rad)
        if lo > hi:
            continue
        v = min(a.speed_mps, b.speed_mps)
        for c in (lo, hi):
            gap = np.linalg.norm(loop_matrix(vehicle, a, c, v, law)
                                 - loop_matrix(vehicle, b, c, v, law))
            if best is None or gap > best[0]:
                best = (gap, a, b, c, v)
    return best[1:]


def build(table, pair, plant, conditions):
    """Controller + Saturation + ``plant``, the design request alternating every frame;
    ``conditions``: (stiffness, friction, speed, curvature)."""
    vehicle, settings = table.vehicle, table.settings
    stiffness, friction, speed, curvature = conditions
    b = DiagramBuilder()
    ctrl = b.AddSystem(SwitchingL1Controller(vehicle=vehicle, designs=list(pair),
                                             settings=settings, options=SwitchingOptions(
                                                 law=settings.controller.adaptation_law,
                                                 initial_speed_mps=speed,
                                                 curvature_preview=False)))
    b.AddSystem(plant)
    limit = vehicle.steering_limit_rad
    sat = b.AddSystem(Saturation([-limit], [limit]))
    for name, value in (("speed_mps", speed), ("curvature_per_m", curvature)):
        source = b.AddSystem(ConstantVectorSource([value]))
        b.Connect(source.get_output_port(), ctrl.GetInputPort(name))
        b.Connect(source.get_output_port(), plant.GetInputPort(name))
    for name, value in (("stiffness_n_per_rad", stiffness), ("friction_mu", friction)):
        b.Connect(b.AddSystem(ConstantVectorSource([value])).get_output_port(),
                  plant.GetInputPort(name))
    times = np.arange(0.0, DURATION_S + FRAME_S, FRAME_S)
    request = (np.arange(times.size) % 2).astype(float).reshape(1, -1)
    b.Connect(b.AddSystem(TrajectorySource(PiecewisePolynomial.ZeroOrderHold(
        times, request))).get_output_port(), ctrl.GetInputPort("design_index"))
    b.Connect(plant.GetOutputPort("state"), ctrl.GetInputPort("state"))
    b.Connect(ctrl.GetOutputPort("steering_rad"), sat.get_input_port())
    b.Connect(sat.get_output_port(), plant.GetInputPort("steering_rad"))
    return b, ctrl


def switched_run(table, pair, stiffness, speed):
    """The design model: logs of s, u and the design in force every 1 ms."""
    plant = LinearLateralPlant(table.vehicle)
    b, ctrl = build(table, pair, plant, (stiffness, 0.5, speed, 0.0))
    ports = {"s": plant.GetOutputPort("state"), "u": ctrl.GetOutputPort("steering_rad"),
             "design": ctrl.GetOutputPort("active_design_index")}
    logs = {k: LogVectorOutput(port, b, 0.001) for k, port in ports.items()}
    simulator = Simulator(b.Build())
    ApplySimulatorConfig(simulator_config(table.settings, "piecewise_constant"), simulator)
    context = simulator.get_mutable_context()
    plant.GetSubsystemByName("eq_2_45").GetMyMutableContextFromRoot(context) \
        .SetContinuousState(S0)
    ctrl.set_initial_state(context, S0, 0.0)
    simulator.AdvanceTo(DURATION_S)
    out = {k: log.FindLog(simulator.get_context()).data() for k, log in logs.items()}
    out["t"] = logs["s"].FindLog(simulator.get_context()).sample_times()
    return out


def test_switching_every_frame_the_l1_loop_stays_inside_its_lyapunov_bound(family):
    table, designs, certificate = family
    assert certificate.method == "common" and certificate.loop_lyapunov_matrix is not None
    a, b, stiffness, speed = worst_pair(table.vehicle, designs, certificate.loop_law)
    run = switched_run(table, (a, b), stiffness, speed)
    t, s, u = run["t"], run["s"], run["u"][0]
    design = run["design"][0].astype(int)
    assert np.count_nonzero(np.diff(design)) >= DURATION_S / FRAME_S - 2  # every frame
    assert np.abs(u).max() < table.vehicle.steering_limit_rad  # linear: never saturated
    zeta = np.vstack([s, u])  # straight road: u - u_ff = u
    p = np.array(certificate.loop_lyapunov_matrix)
    lyapunov = np.einsum("it,ij,jt->t", zeta, p, zeta)
    rate = certificate.loop_decay_rate_per_s
    assert np.all(lyapunov <= np.exp(-2.0 * rate * t) * lyapunov[0] * (1.0 + 1e-6))
    e1_bound = np.sqrt(lyapunov[0] * np.linalg.inv(p)[0, 0]) * np.exp(-rate * t)
    assert np.all(np.abs(s[0]) <= e1_bound)
    assert abs(s[0, -1]) < 0.1 * S0[0]  # and the offset is gone


# ------------------------------------------------------------------ the nonlinear plant

def true_uncertainty(vehicle, p, s, u, u_ad, plant_inputs):
    """What design p's predictor should estimate at this instant on the nonlinear plant:
    ``s' - A_m s - b_m (u_ad + u_ff) - g_hat V kappa`` (straight or constant curvature)."""
    s_dot = nonlinear_error_derivatives(vehicle, s, plant_inputs)
    kappa = plant_inputs.curvature
    return (s_dot - p.a_m @ s - p.b_m * (u_ad + l1_law.curvature_feedforward(p, kappa))
            - p.g_hat * p.speed_mps * kappa)


def nonlinear_switched_run(table, pair, conditions, s0):
    """The nonlinear plant, stepped sample by sample. At every sample t_k, before the
    controller's update: the estimate of the design in force (from its prediction error) and
    its true uncertainty; at a switch also the estimate the new design applies (the hand-over,
    checked against the controller's own state after the update) and the new design's true
    uncertainty. Errors are in the filter's units, ``r (sigma_hat - sigma)`` (rad)."""
    vehicle, settings = table.vehicle, table.settings
    stiffness, friction, speed, curvature = conditions
    plant = NonlinearLateralPlant(vehicle)
    b, ctrl = build(table, pair, plant, conditions)
    diagram = b.Build()
    simulator = Simulator(diagram)
    ApplySimulatorConfig(simulator_config(settings, "piecewise_constant"), simulator)
    context = simulator.get_mutable_context()
    plant.body_state_subsystem().GetMyMutableContextFromRoot(context).SetContinuousState(
        body_state_from_error(s0, speed, curvature))
    ctrl.set_initial_state(context, s0, curvature)
    law = ctrl.law_system()
    t_s = settings.controller.sample_period_s
    out = {"e1": [], "u_step": [], "error": [], "switch_error": [], "dropped": [],
           "switches": 0}
    previous_u = None
    for k in range(1, round(DURATION_S / t_s)):
        simulator.AdvanceTo(k * t_s)  # the update at t_k is pending
        z = law.GetMyContextFromRoot(context).get_discrete_state_vector().CopyToVector()
        s = plant.GetOutputPort("state").Eval(plant.GetMyContextFromRoot(context))
        u = float(ctrl.GetOutputPort("steering_rad").Eval(ctrl.GetMyContextFromRoot(context))[0])
        inputs = PlantInputs(u, stiffness, friction, speed, curvature)
        p = law.law_at(int(z[DESIGN]), int(z[GRID])).parameters
        estimate = l1_law.piecewise_constant_estimate(
            p, l1_law.predicted_measurement(p, z[S_HAT], curvature) - s)
        truth = true_uncertainty(vehicle, p, s, u, z[U_AD], inputs)
        out["error"].append(float(p.pc_output_inverse @ (estimate - truth)))
        out["e1"].append(float(s[0]))
        requested = round(float(ctrl.GetInputPort("design_index").Eval(
            ctrl.GetMyContextFromRoot(context))[0]))  # the request the update will read
        if requested != int(z[DESIGN]):
            new = law.law_at(requested, int(z[GRID])).parameters
            q_new, u_ad_new = l1_law.piecewise_constant_hand_over(
                p, new, z[S_HAT], z[U_AD], l1_law.SwitchSample(s, curvature))
            carried = l1_law.piecewise_constant_estimate(
                new, l1_law.predicted_measurement(new, q_new, curvature) - s)
            truth_new = true_uncertainty(vehicle, new, s, u, u_ad_new, inputs)
            out["switch_error"].append(float(new.pc_output_inverse @ (carried - truth_new)))
            out["dropped"].append(float(new.pc_output_inverse @ truth_new))  # a restart's loss
            simulator.AdvanceTo(k * t_s + 1e-6)  # the update applied
            after = law.GetMyContextFromRoot(context).get_discrete_state_vector().CopyToVector()
            decay = np.exp(-new.filter_gain * t_s)
            assert int(after[DESIGN]) == requested
            assert after[U_AD] == pytest.approx(
                decay * u_ad_new - (1 - decay) * float(new.pc_output_inverse @ carried),
                rel=1e-9, abs=1e-12)  # the controller applied that estimate
            u_after = float(ctrl.GetOutputPort("steering_rad").Eval(
                ctrl.GetMyContextFromRoot(context))[0])
            out["u_step"].append(abs(u_after - u))
            out["switches"] += 1
        previous_u = u
    assert previous_u is not None
    return {k: np.asarray(v) if isinstance(v, list) else v for k, v in out.items()}


@pytest.mark.parametrize("road", ["straight", "design_radius"])
def test_switching_every_frame_on_the_nonlinear_plant_carries_the_estimate(family, road):
    table, designs, certificate = family
    a, b, _, speed = worst_pair(table.vehicle, designs, certificate.loop_law)
    stiffness = max(a.stiffness_lo_n_per_rad, b.stiffness_lo_n_per_rad)  # the least both hold
    friction = max(a.friction_mu_lo, b.friction_mu_lo)
    curvature = 0.0 if road == "straight" else 1.0 / table.settings.synthesis.design_radius_m
    s0 = S0 if road == "straight" else np.zeros(4)
    run = nonlinear_switched_run(table, (a, b), (stiffness, friction, speed, curvature), s0)
    assert run["switches"] >= DURATION_S / FRAME_S - 2
    between = np.abs(run["error"][200:]).max()  # after the first 0.2 s
    # nothing drops out: the estimate a new design applies is as good as any other, and a
    # hundredth at most of what restarting the predictor (no estimate for a sample) would drop
    worst = np.abs(run["switch_error"]).max()
    assert worst <= 3.0 * between + 1e-7
    assert worst <= 0.01 * np.abs(run["dropped"]).max()
    # the steering moves at a switch by at most one sample's filter step (bumpless)
    assert run["u_step"].max() < 0.01
    e1 = np.abs(run["e1"])
    assert e1.max() <= max(abs(s0[0]), 0.0) + 0.2
    assert e1[-1000:].max() < 0.05  # settled in lane in the last second
    print(f"{road}: {run['switches']} switches at {speed:.2f} m/s, C {stiffness:.0f} N/rad; "
          f"peak |e1| {e1.max():.4f} m, last 1 s {e1[-1000:].max():.4f} m; estimate error "
          f"(filter units) at switches {np.abs(run['switch_error']).max():.2e} rad, between "
          f"{between:.2e} rad (a restart would drop up to {np.abs(run['dropped']).max():.2e} "
          f"rad); largest steering step at a switch {run['u_step'].max():.2e} rad")
