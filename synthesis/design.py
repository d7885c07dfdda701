"""The design object: what synthesis produces and the controller consumes.

One ``ControllerDesign`` per certified stiffness interval (a contiguous label range, or a
regression interval). Saved as YAML with a schema version and provenance (see
``synthesis.design_io``); the state-feedback gain is stored under the key ``k_m``.
"""

import dataclasses

import numpy as np

from drake_cert.dynamics import fiala_secant_ratio


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
    margins: dict[str, float] = dataclasses.field(default_factory=dict)
    # normalised tire slip bound z_b = C |tan a| / (3 mu_lo F_z) the design admits (DESIGN
    # 5.3d): it covers the Fiala secant stiffness down to C_lo (1 - z_b + z_b^2/3); 0 means a
    # linear tire (the certified interval is the label interval)
    tire_slip_bound: float = 0.0
    certified_law: str = "piecewise_constant"  # adaptation law conditions b and c are for

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
