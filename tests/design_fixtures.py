"""Small controller designs for the systems tests (no synthesis run needed)."""

import dataclasses

import numpy as np
import scipy.linalg

from drake_cert.dynamics import lateral_error_dynamics
from drake_cert.synthesis.design import ControllerDesign


def lqr_design(vehicle, stiffness_lo, stiffness_hi, speed_mps, filter_gain=200.0,
               labels=("test",)) -> ControllerDesign:
    """A ControllerDesign with an LQR k_m for the nominal (C_hat, V): A_m Hurwitz by construction.

    Q = diag(1, 0.1, 1, 0.1), R = 10 on the eq. 2.45 model at the interval midpoint.
    """
    c_hat = 0.5 * (stiffness_lo + stiffness_hi)
    a, b, _ = lateral_error_dynamics(vehicle, c_hat, speed_mps)
    r = 10.0
    p = scipy.linalg.solve_continuous_are(a, b.reshape(4, 1), np.diag([1.0, 0.1, 1.0, 0.1]),
                                          np.array([[r]]))
    k_m = (b @ p) / r
    return ControllerDesign(labels=list(labels), stiffness_lo_n_per_rad=stiffness_lo,
                            stiffness_hi_n_per_rad=stiffness_hi, nominal_stiffness_n_per_rad=c_hat,
                            friction_mu_lo=0.5, k_m=[float(x) for x in k_m],
                            gain_speed_max_mps=30.0, filter_gain=filter_gain,
                            speed_mps=speed_mps)


@dataclasses.dataclass(frozen=True)
class FakeDecision:
    """The fields of drake_cert.systems.certified_interval.Decision that LongitudinalMotion
    reads."""

    time_s: float
    position_m: float
    speed_command_mps: float
    design_index: int
