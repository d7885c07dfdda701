"""The whole L1 loop under the worst switching the route rules allow (docs/design.md 5.6).

Claim: with the jointly synthesized robotcar-like designs, switching every camera frame (0.1 s)
between the two designs whose L1 reference loops differ most, the loop's state
``z = [s, u_ad]`` keeps ``z' P_z z <= e^(-2 lambda_z t) z(0)' P_z z(0)`` and so
``|e1(t)| <= sqrt(z(0)' P_z z(0) (P_z^-1)_11) e^(-lambda_z t)``, with ``P_z, lambda_z`` the
family's loop certificate. The run is the real switching controller (piecewise-constant law,
T_s = 1 ms, predictor restarted at each switch, u_ad handed over) on the design model
(``LinearLateralPlant``), on a straight road, at a stiffness and speed inside both designs'
ranges, from a 0.5 m offset.
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
from drake_cert.synthesis.switching import common_lyapunov_certificate, switching_families
from drake_cert.systems.closed_loop import simulator_config
from drake_cert.systems.plants import LinearLateralPlant
from drake_cert.systems.switching_controller import SwitchingL1Controller, SwitchingOptions

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


def worst_pair(vehicle, designs, law):
    """The two designs with overlapping intervals whose reference matrices differ most (at an
    end of the overlap, at the slower design's speed); returns (a, b, C, V)."""
    best = None
    for a, b in itertools.combinations(designs, 2):
        lo = max(a.certified_interval[0], b.certified_interval[0])
        hi = min(a.certified_interval[1], b.certified_interval[1])
        if lo > hi:
            continue
        v = min(a.speed_mps, b.speed_mps)
        for c in (lo, hi):
            gap = np.linalg.norm(
                reference_system_matrix(vehicle, a.k_m, a.nominal_stiffness_n_per_rad, c, v,
                                        a.filter_gain, law)
                - reference_system_matrix(vehicle, b.k_m, b.nominal_stiffness_n_per_rad, c, v,
                                          b.filter_gain, law))
            if best is None or gap > best[0]:
                best = (gap, a, b, c, v)
    return best[1:]


def switched_run(table, pair, stiffness, speed):
    """Controller + Saturation + linear plant, the design request alternating every frame."""
    vehicle, settings = table.vehicle, table.settings
    law = settings.controller.adaptation_law
    b = DiagramBuilder()
    ctrl = b.AddSystem(SwitchingL1Controller(vehicle=vehicle, designs=list(pair),
                                             settings=settings, options=SwitchingOptions(
                                                 law=law, initial_speed_mps=speed,
                                                 curvature_preview=False)))
    plant = b.AddSystem(LinearLateralPlant(vehicle))
    limit = vehicle.steering_limit_rad
    sat = b.AddSystem(Saturation([-limit], [limit]))
    for name, value in (("speed_mps", speed), ("curvature_per_m", 0.0)):
        source = b.AddSystem(ConstantVectorSource([value]))
        b.Connect(source.get_output_port(), ctrl.GetInputPort(name))
        b.Connect(source.get_output_port(), plant.GetInputPort(name))
    for name, value in (("stiffness_n_per_rad", stiffness), ("friction_mu", 0.5)):
        b.Connect(b.AddSystem(ConstantVectorSource([value])).get_output_port(),
                  plant.GetInputPort(name))
    times = np.arange(0.0, DURATION_S + FRAME_S, FRAME_S)
    request = (np.arange(times.size) % 2).astype(float).reshape(1, -1)
    b.Connect(b.AddSystem(TrajectorySource(PiecewisePolynomial.ZeroOrderHold(
        times, request))).get_output_port(), ctrl.GetInputPort("design_index"))
    b.Connect(plant.GetOutputPort("state"), ctrl.GetInputPort("state"))
    b.Connect(ctrl.GetOutputPort("steering_rad"), sat.get_input_port())
    b.Connect(sat.get_output_port(), plant.GetInputPort("steering_rad"))
    ports = {"s": plant.GetOutputPort("state"), "u": ctrl.GetOutputPort("steering_rad"),
             "design": ctrl.GetOutputPort("active_design_index")}
    logs = {k: LogVectorOutput(port, b, 0.001) for k, port in ports.items()}
    simulator = Simulator(b.Build())
    ApplySimulatorConfig(simulator_config(settings, law), simulator)
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
    law = certificate.loop_law
    a, b, stiffness, speed = worst_pair(table.vehicle, designs, law)
    run = switched_run(table, (a, b), stiffness, speed)
    t, s, u = run["t"], run["s"], run["u"][0]
    design = run["design"][0].astype(int)
    assert np.count_nonzero(np.diff(design)) >= DURATION_S / FRAME_S - 2  # every frame
    limit = table.vehicle.steering_limit_rad
    assert np.abs(u).max() < limit  # the saturation never engages: the loop is linear
    # u = -k_sigma s + u_ad (straight road: no feedforward), so u_ad = u + k_sigma s
    k_in_force = np.array([(a, b)[i].k_m for i in design])
    z = np.vstack([s, u + np.einsum("ij,ji->i", k_in_force, s)])
    p = np.array(certificate.loop_lyapunov_matrix)
    lyapunov = np.einsum("it,ij,jt->t", z, p, z)
    rate = certificate.loop_decay_rate_per_s
    assert np.all(lyapunov <= np.exp(-2.0 * rate * t) * lyapunov[0] * (1.0 + 1e-6))
    e1_bound = np.sqrt(lyapunov[0] * np.linalg.inv(p)[0, 0]) * np.exp(-rate * t)
    assert np.all(np.abs(s[0]) <= e1_bound)
    assert abs(s[0, -1]) < 0.1 * S0[0]  # and the offset is gone
