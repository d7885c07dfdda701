"""The design object: what synthesis produces and the controller consumes.

One ``ControllerDesign`` per certified stiffness interval (a contiguous label range, or a
regression interval). Saved as YAML with a schema version and provenance (see
``drake_cert.synthesis.design_io``); the state-feedback gain is stored under the key ``k_m``.
"""

import dataclasses

import numpy as np

from drake_cert.dynamics import fiala_secant_ratio

# The keys of ControllerDesign.margins (units in the name); each is > 0 where its condition
# holds. Kept here, with the design that stores them, so that reading a design file needs no
# solver import; ``drake_cert.synthesis.conditions`` re-exports them.
MARGIN_KEYS = {
    "gain_decay_per_s": "alpha-shifted stability of A - b k_m: -(max Re eig) - alpha",
    "l1_condition": "1 - ||G||_L1 L (dimensionless)",
    "reference_stability_per_s": "-(max Re eig) of the reference system over [V_min, V]",
    "steady_state_lane_margin_m": "lane margin left at the adaptive equilibrium on the design "
                                  "curve: lane_margin_m - max_C |e1| (m)",
    "grip_normalised_slip": "normalised_slip_max - steady tire slip z at mu_lo (Fiala)",
    "grip_lateral_accel_mps2": "lateral_accel_fraction mu_lo g - V^2 / R",
    # condition e, each only where its limit is given (VEHICLE_LIMIT_KEYS)
    "rollover_lateral_accel_mps2": "rollover_fraction g t / (2 h) - V^2 / R",
    "comfort_lateral_accel_mps2": "lateral_accel_limit_mps2 - V^2 / R",
}
VEHICLE_LIMIT_KEYS = ("rollover_lateral_accel_mps2", "comfort_lateral_accel_mps2")


@dataclasses.dataclass
class ControllerDesign:
    """Gains and safe speed synthesized for every stiffness in ``[stiffness_lo, stiffness_hi]``.

    ``speed_mps`` is the largest speed at which every condition of DESIGN 5.3 holds; 0 means
    no safe speed (the car stops) and ``failed_condition`` names the condition that failed.
    ``nominal_stiffness_n_per_rad`` is the midpoint of :attr:`certified_interval`.
    """

    labels: list[str]  # label names of the range, grippiest first ([] for regression)
    stiffness_lo_n_per_rad: float
    stiffness_hi_n_per_rad: float
    nominal_stiffness_n_per_rad: float  # C_hat, the interval midpoint
    friction_mu_lo: float  # least friction of the range (grip condition)
    k_m: list[float]  # state feedback u = -k_m s (rad per state unit), 4 entries
    gain_speed_max_mps: float  # k_m is certified (corner LMI) on [speed_min, this]
    filter_gain: float  # k of D(s) = 1/s; filter bandwidth is k * w (rad/s)
    speed_mps: float  # safe design speed (m/s); 0: stop
    failed_condition: str = ""  # "" when a safe speed exists
    margins: dict[str, float] = dataclasses.field(default_factory=dict)  # MARGIN_KEYS
    # normalised tire slip bound z_b = C |tan a| / (3 mu_lo F_z) the design admits
    # (DESIGN 5.3d): it covers the Fiala secant stiffness down to C_lo (1 - z_b + z_b^2/3);
    # 0 means a linear tire (the certified interval is the label interval)
    tire_slip_bound: float = 0.0
    certified_law: str = "piecewise_constant"  # adaptation law conditions b and c are for
    # what stops the speed rising: the condition that fails just above speed_mps (grip,
    # rollover, comfort, l1_condition, reference_stability, steady_state_offset) or
    # "speed_range" (the top of the searched range); "" with no safe speed, or in a file
    # written before this field existed
    speed_limited_by: str = ""

    @property
    def interval(self) -> tuple[float, float]:
        """The label (or regression) stiffness interval, N/rad, as perception certifies it."""
        return (self.stiffness_lo_n_per_rad, self.stiffness_hi_n_per_rad)

    @property
    def certified_interval(self) -> tuple[float, float]:
        """Effective stiffness interval every condition holds on (N/rad): the label interval
        widened down to the tire's secant stiffness at the slip bound."""
        ratio = float(fiala_secant_ratio(self.tire_slip_bound))
        return (self.stiffness_lo_n_per_rad * ratio, self.stiffness_hi_n_per_rad)

    @property
    def k_m_array(self) -> np.ndarray:
        return np.asarray(self.k_m, dtype=float).reshape(4)

    @property
    def has_safe_speed(self) -> bool:
        return self.speed_mps > 0.0 and not self.failed_condition
