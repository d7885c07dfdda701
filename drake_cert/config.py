"""Typed YAML configuration: vehicle, road conditions and presets, controller and synthesis.

Files are read with Drake's ``yaml_load_typed`` into the dataclasses below. Every field
must be given (no silent defaults), unknown keys are errors, and non-physical values are
rejected; each problem raises one :class:`ConfigError` naming the key and the file.
Physical fields carry a plausible range (:class:`Plausible`, in the field's metadata): a
value outside it is refused with the unit mistake that would explain it ("kN/rad? write
100000"). Keys, types and plausible ranges are checked on the parsed YAML before pydrake is
imported, so a mistake in a file costs no heavy import.
Units are SI; conventions (docs/usage.md, "Conventions"): e1 > 0 left of the lane centre,
curvature > 0 left turn, steering > 0 left, ``psidot_des = V * kappa``.
"""


import dataclasses
import math
import os
import re
import stat
import types
import typing
from importlib import resources
from pathlib import Path

import yaml

from drake_cert.errors import ConfigError

GRAVITY_MPS2 = 9.81


@dataclasses.dataclass(frozen=True)
class Plausible:
    """The range a physical quantity plausibly takes, and the unit mistakes that explain a
    value outside it.

    ``small`` and ``large`` list ``(factor, unit)`` pairs: a value below ``lo`` (above ``hi``)
    that lands in ``[lo, hi]`` once multiplied by ``factor`` was probably written in ``unit``,
    and the message suggests the product (a stiffness of 100 below 1000 N/rad: "kN/rad? write
    100000"). Only positive finite values are judged; the sign is each field's own check.
    """

    lo: float  # smallest plausible value, in the field's unit
    hi: float  # largest plausible value, in the field's unit
    unit: str  # the field's unit as printed ("N/rad", "kg", "m"); "" for a pure number
    what: str  # what the field is, after "for" ("a vehicle mass")
    small: tuple[tuple[float, str], ...] = ()
    large: tuple[tuple[float, str], ...] = ()

    def problem(self, value: float) -> str | None:
        """None if ``value`` is plausible (or not a positive finite number), else the reason:
        "100 N/rad is implausibly small for ... (kN/rad? write 100000)"."""
        if isinstance(value, bool) or not isinstance(value, (int, float)) \
                or not (math.isfinite(value) and value > 0) or self.lo <= value <= self.hi:
            return None
        low = value < self.lo
        unit = f" {self.unit}" if self.unit else ""
        hints = [f"{name}? write {value * factor:.6g}"
                 for factor, name in (self.small if low else self.large)
                 if self.lo <= value * factor <= self.hi]
        bound = f"{'below' if low else 'above'} {self.lo if low else self.hi:g}{unit}"
        return (f"{value:g}{unit} is implausibly {'small' if low else 'large'} for "
                f"{self.what}, {bound}" + (f" ({'; '.join(hints)})" if hints else ""))

    def check(self, value: float, key: str, where: str | None = None) -> None:
        """Raise :class:`ConfigError` "``where``: ``key`` = ... (hint)" for an implausible value
        (a command-line option as ``key``: "--stiffness 100 N/rad is ...")."""
        reason = self.problem(value)
        if reason is not None:
            raise ConfigError(f"{where + ': ' if where else ''}{_assign(key)}{reason}")


def _assign(key: str) -> str:
    """"key = " for a file's key, "--option " for a command-line option."""
    return f"{key} " if key.startswith("--") else f"{key} = "


MM_OR_CM = ((1e-3, "mm"), (1e-2, "cm"))
# per-tire cornering stiffness: passenger-car tires are 20-150 kN/rad, truck tires up to ~400
STIFFNESS_PLAUSIBLE = Plausible(1_000.0, 2_000_000.0, "N/rad",
                                "a cornering stiffness per tire", small=((1e3, "kN/rad"),))
SPEED_PLAUSIBLE = Plausible(0.0, 100.0, "m/s", "a road vehicle's speed",
                            large=((1 / 3.6, "km/h"),))


def _plausible(default: float, plausible: Plausible, **metadata) -> typing.Any:
    """A dataclass field with a plausible range (checked by the loader and ``validate``)."""
    return dataclasses.field(default=default, metadata={"plausible": plausible, **metadata})


def check_plausible_fields(obj: typing.Any, prefix: str, where: str) -> None:
    """:meth:`Plausible.check` on every field of the dataclass ``obj`` that declares a range."""
    for f in dataclasses.fields(obj):
        if "plausible" in f.metadata and getattr(obj, f.name) is not None:
            f.metadata["plausible"].check(getattr(obj, f.name), prefix + f.name, where)


# frames are 3 x size x size float32 tensors, evaluated in batches of noisy copies
FRAME_SIZE_MAX = 1024  # pixels: 12 MiB a frame; the shipped models take 64


def check_frame_size(size: int, key: str, batch_size: int | None = None) -> None:
    """Refuse a frame side (pixels) whose frames would not fit in memory, saying how much
    they would take: ``ConfigError("<key> = 100000 px: one 100000x100000 RGB frame takes
    112 GiB in float32 (...); the limit is 1024 px")``. ``key`` names the option ("--size")
    or the field ("where: camera.frame_size")."""
    if isinstance(size, bool) or not isinstance(size, int) or size <= FRAME_SIZE_MAX:
        return
    frame = 3 * 4 * size * size
    batch = (f", a batch of {batch_size} noisy copies {_bytes(frame * batch_size)}"
             if batch_size and batch_size > 1 else "")
    raise ConfigError(f"{_assign(key)}{size} px: one {size}x{size} RGB frame takes {_bytes(frame)} "
                      f"in float32{batch}; the limit is {FRAME_SIZE_MAX} px "
                      f"({_bytes(3 * 4 * FRAME_SIZE_MAX**2)} a frame; the shipped models take "
                      "64 px)")


def _bytes(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if n < 1024 or unit == "TiB":
            return f"{n:.3g} {unit}"
        n /= 1024
    raise AssertionError("unreachable")


@dataclasses.dataclass
class VehicleParams:
    """Single-track vehicle (Rajamani ch. 2-3) with its tires and, optionally, its roll geometry.

    Tires (docs/design.md 2.1): a front tire's cornering stiffness is ``tire_stiffness_scale``
    times the road condition's (the conditions table's C, N/rad), a rear tire's
    ``rear_tire_stiffness_scale`` times it (the front scale when absent); so C_f = C and
    C_r = ``rear_stiffness_ratio`` C for the front per-tire stiffness C the designs are stated
    in. ``cg_height_m`` and ``track_width_m`` (both or neither) give the static stability factor
    t / (2 h) that limits the safe speed (DESIGN 5.3e).

    Plausible ranges (refused outside, with the likely unit mistake): mass 100-200,000 kg,
    yaw inertia 50-5,000,000 kg m^2, CG-to-axle distances 0.3-10 m, lane width 1-20 m, car
    width 0.5-5 m, tire stiffness scales 0.1-10, CG height 0.1-5 m, track width 0.5-5 m."""

    mass_kg: float = _plausible(1573.0, Plausible(  # m
        100.0, 200_000.0, "kg", "a vehicle mass", small=((1e3, "tonnes"),),
        large=((1e-3, "g"),)))
    yaw_inertia_kg_m2: float = _plausible(2873.0, Plausible(  # I_z
        50.0, 5_000_000.0, "kg m^2", "a yaw moment of inertia", small=((1e3, "t m^2"),)))
    lf_m: float = _plausible(1.1, Plausible(  # CG to front axle
        0.3, 10.0, "m", "a CG-to-axle distance", large=MM_OR_CM))
    lr_m: float = _plausible(1.58, Plausible(  # CG to rear axle
        0.3, 10.0, "m", "a CG-to-axle distance", large=MM_OR_CM))
    steering_limit_rad: float = 0.5  # |u| saturation
    lane_width_m: float = _plausible(3.5, Plausible(1.0, 20.0, "m", "a lane width",
                                                    large=MM_OR_CM))
    car_width_m: float = _plausible(1.8, Plausible(0.5, 5.0, "m", "a car width",
                                                   large=MM_OR_CM))
    # factor on the conditions table's per-tire stiffness intervals for this vehicle's tires
    # (dimensionless; optional key, default 1): designs are synthesized and verified on
    # [scale C_lo, scale C_hi] of each label (ConditionsTable.with_stiffness_scale)
    tire_stiffness_scale: float = _plausible(1.0, Plausible(
        0.1, 10.0, "", "a factor on the conditions table's stiffness (not a stiffness)"),
        optional=True)
    # the rear tires' factor (dimensionless; optional: absent = tire_stiffness_scale, then
    # that factor is the front tires' only)
    rear_tire_stiffness_scale: float | None = _plausible(None, Plausible(
        0.1, 10.0, "", "a factor on the conditions table's stiffness (not a stiffness)"),
        optional=True)
    # height of the centre of gravity above the road (m; optional, with track_width_m)
    cg_height_m: float | None = _plausible(None, Plausible(
        0.1, 5.0, "m", "a CG height", large=MM_OR_CM), optional=True)
    # track width, tire centre to tire centre (m; optional, with cg_height_m; mean of the axles)
    track_width_m: float | None = _plausible(None, Plausible(
        0.5, 5.0, "m", "a track width", large=MM_OR_CM), optional=True)

    @property
    def lane_margin_m(self) -> float:
        """Largest |e1| with the car still inside its lane: (lane - car) / 2."""
        return 0.5 * (self.lane_width_m - self.car_width_m)

    def with_defaults(self) -> "VehicleParams":
        """The vehicle as loaded: an absent rear scale is the front scale (one scale on both
        axles), so that a file with one scale and one giving both equal are the same vehicle."""
        if self.rear_tire_stiffness_scale is not None:
            return self
        return dataclasses.replace(self, rear_tire_stiffness_scale=self.tire_stiffness_scale)

    @property
    def rear_stiffness_ratio(self) -> float:
        """C_r / C_f of one tire each (dimensionless; 1 when the file gives one scale)."""
        if self.rear_tire_stiffness_scale is None:
            return 1.0
        return self.rear_tire_stiffness_scale / self.tire_stiffness_scale

    @property
    def static_stability_factor(self) -> float | None:
        """t / (2 h): the lateral acceleration in g at which a rigid vehicle tips (None when
        the file gives no CG height and track width)."""
        if self.cg_height_m is None or self.track_width_m is None:
            return None
        return self.track_width_m / (2.0 * self.cg_height_m)

    def validate(self, where: str = "vehicle") -> None:
        for key in ("mass_kg", "yaw_inertia_kg_m2", "lf_m", "lr_m", "steering_limit_rad",
                    "lane_width_m", "car_width_m", "tire_stiffness_scale"):
            _require_positive(getattr(self, key), key, where)
        for key in ("rear_tire_stiffness_scale", "cg_height_m", "track_width_m"):
            if getattr(self, key) is not None:
                _require_positive(getattr(self, key), key, where)
        check_plausible_fields(self, "", where)
        if (self.cg_height_m is None) != (self.track_width_m is None):
            given, other = (("cg_height_m", "track_width_m") if self.track_width_m is None
                            else ("track_width_m", "cg_height_m"))
            raise ConfigError(f"{where}: {given} is given without {other}; the rollover limit "
                              "needs both (or leave both out)")
        if self.track_width_m is not None and self.track_width_m >= self.car_width_m:
            raise ConfigError(f"{where}: track_width_m ({self.track_width_m}) must be less than "
                              f"car_width_m ({self.car_width_m}): the track is measured between "
                              "tire centres, inside the body")
        if self.steering_limit_rad >= 0.5 * math.pi:
            raise ConfigError(f"{where}: steering_limit_rad = {self.steering_limit_rad} must be "
                              f"below pi/2 = {0.5 * math.pi:.6f} rad (the plant's tan(u) is "
                              "singular there); is it in degrees?")
        if self.car_width_m >= self.lane_width_m:
            raise ConfigError(f"{where}: car_width_m ({self.car_width_m}) must be less than "
                              f"lane_width_m ({self.lane_width_m})")


@dataclasses.dataclass
class RoadCondition:
    """One road condition: cornering-stiffness interval per tire (N/rad) and friction mu."""

    name: str = ""
    stiffness_lo_n_per_rad: float = _plausible(0.0, STIFFNESS_PLAUSIBLE)
    stiffness_hi_n_per_rad: float = _plausible(0.0, STIFFNESS_PLAUSIBLE)
    # (0, 2] is checked by ConditionsTable.validate; the range here catches a percentage
    friction_mu: float = _plausible(0.0, Plausible(0.0, 2.0, "", "a friction coefficient",
                                                   large=((1e-2, "percent"),)))

    @property
    def interval(self) -> tuple[float, float]:
        return (self.stiffness_lo_n_per_rad, self.stiffness_hi_n_per_rad)


@dataclasses.dataclass
class Preset:
    """A data set's label list (grippiest first) and frames per class."""

    name: str = ""
    labels: list[str] = dataclasses.field(default_factory=list)
    frames_per_class: int = 0


@dataclasses.dataclass
class ConditionsTable:
    """The paper's Table (cornering stiffness per condition) plus friction, and the presets."""

    conditions: list[RoadCondition] = dataclasses.field(default_factory=list)
    presets: list[Preset] = dataclasses.field(default_factory=list)

    def condition(self, name: str) -> RoadCondition:
        for c in self.conditions:
            if c.name == name:
                return c
        raise ConfigError(f"unknown road condition {name!r}; known: "
                          f"{', '.join(c.name for c in self.conditions)}")

    def preset(self, name: str) -> Preset:
        for p in self.presets:
            if p.name == name:
                return p
        raise ConfigError(f"unknown preset {name!r}; known: "
                          f"{', '.join(p.name for p in self.presets)}")

    def preset_conditions(self, preset: str) -> list[RoadCondition]:
        """The preset's conditions in its label order (grippiest first)."""
        return [self.condition(n) for n in self.preset(preset).labels]

    def safe_set(self, preset: str, label: str) -> list[str]:
        """S(l): labels of the preset whose friction is <= mu(l) (paper Table, safety class set)."""
        mu = self.condition(label).friction_mu
        return [c.name for c in self.preset_conditions(preset) if c.friction_mu <= mu]

    def contiguous_ranges(self, preset: str) -> list[list[str]]:
        """Every run of consecutive labels in the preset's friction order (singles included)."""
        labels = self.preset(preset).labels
        return [labels[i:j] for i in range(len(labels)) for j in range(i + 1, len(labels) + 1)]

    def hull(self, labels: typing.Iterable[str]) -> tuple[float, float]:
        """Smallest stiffness interval containing every label's interval (N/rad)."""
        conds = [self.condition(n) for n in labels]
        if not conds:
            raise ConfigError("hull of an empty label set")
        return (min(c.stiffness_lo_n_per_rad for c in conds),
                max(c.stiffness_hi_n_per_rad for c in conds))

    def with_stiffness_scale(self, scale: float) -> "ConditionsTable":
        """This table with every stiffness interval multiplied by ``scale`` (a vehicle's
        ``tire_stiffness_scale``; friction unchanged). Returns ``self`` for 1."""
        if scale == 1.0:
            return self
        return dataclasses.replace(self, conditions=[
            dataclasses.replace(c, stiffness_lo_n_per_rad=c.stiffness_lo_n_per_rad * scale,
                                stiffness_hi_n_per_rad=c.stiffness_hi_n_per_rad * scale)
            for c in self.conditions])

    def envelope(self, preset: str) -> tuple[float, float]:
        """The preset's most conservative interval: the hull of all its labels (N/rad)."""
        return self.hull(self.preset(preset).labels)

    def least_friction(self, labels: typing.Iterable[str]) -> float:
        """Smallest friction coefficient among the labels."""
        return min(self.condition(n).friction_mu for n in labels)

    def validate(self, where: str = "conditions") -> None:
        names = [c.name for c in self.conditions]
        if not names:
            raise ConfigError(f"{where}: conditions: at least one road condition is required")
        if len(set(names)) != len(names):
            raise ConfigError(f"{where}: conditions: duplicate names in {names}")
        for i, c in enumerate(self.conditions):
            key = f"conditions[{i}] ({c.name})"
            if not c.name:
                raise ConfigError(f"{where}: conditions[{i}].name must not be empty")
            _require_positive(c.stiffness_lo_n_per_rad, f"{key}.stiffness_lo_n_per_rad", where)
            check_plausible_fields(c, f"{key}.", where)
            if c.stiffness_lo_n_per_rad >= c.stiffness_hi_n_per_rad:
                raise ConfigError(
                    f"{where}: {key}: stiffness_lo_n_per_rad ({c.stiffness_lo_n_per_rad}) must be "
                    f"less than stiffness_hi_n_per_rad ({c.stiffness_hi_n_per_rad})")
            if not 0.0 < c.friction_mu <= 2.0:
                raise ConfigError(f"{where}: {key}.friction_mu = {c.friction_mu} is not in (0, 2]")
        pnames = [p.name for p in self.presets]
        if len(set(pnames)) != len(pnames):
            raise ConfigError(f"{where}: presets: duplicate names in {pnames}")
        for i, p in enumerate(self.presets):
            key = f"presets[{i}] ({p.name})"
            if not p.labels:
                raise ConfigError(f"{where}: {key}.labels must not be empty")
            if len(set(p.labels)) != len(p.labels):
                raise ConfigError(f"{where}: {key}.labels has duplicates: {p.labels}")
            for n in p.labels:
                if n not in names:
                    raise ConfigError(f"{where}: {key}.labels: unknown condition {n!r}")
            mus = [self.condition(n).friction_mu for n in p.labels]
            if any(a < b for a, b in zip(mus, mus[1:], strict=False)):
                raise ConfigError(f"{where}: {key}.labels must be ordered grippiest first "
                                  f"(friction non-increasing), got mu = {mus}")
            if p.frames_per_class <= 0:
                raise ConfigError(f"{where}: {key}.frames_per_class = {p.frames_per_class} "
                                  "must be positive")


MAX_SAMPLE_PERIOD_S = 0.02  # longest controller.sample_period_s accepted (50 Hz)


@dataclasses.dataclass
class ControllerSettings:
    """L1 adaptive controller settings (DESIGN section 4)."""

    adaptation_law: str = "piecewise_constant"  # "piecewise_constant" or "gradient"
    adaptation_gain: float = 1.0e4  # Gamma of the gradient law (1/s)
    q_ad_diag: list[float] = dataclasses.field(default_factory=lambda: [10.0, 1.0, 10.0, 1.0])
    sample_period_s: float = 1.0e-3  # T_s of the piecewise-constant law
    projection_epsilon: float = 0.1  # epsilon of the projection operator's convex function
    bound_factor: float = 1.1  # parameter sets are this factor times the largest value
    # smallest road radius (m) the adaptation sets cover: the gradient law's bound on |sigma|
    # is taken at curvature 1 / this; default half the design radius, a margin of 2 on the
    # largest curvature a design admits (drake_cert.systems.l1_law, "Projection bound")
    min_radius_m: float = dataclasses.field(default=25.0, metadata={"optional": True})
    # road preview of the curvature feedforward (DESIGN 4): u_ff is taken at the mean
    # curvature over the travel window [t + ahead - window, t + ahead] (s); window 0: off
    preview_ahead_s: float = dataclasses.field(default=0.4, metadata={"optional": True})
    preview_window_s: float = dataclasses.field(default=0.4, metadata={"optional": True})

    def validate(self, where: str = "settings") -> None:
        if self.adaptation_law not in ("piecewise_constant", "gradient"):
            raise ConfigError(f"{where}: controller.adaptation_law = {self.adaptation_law!r}; "
                              "expected 'piecewise_constant' or 'gradient'")
        _require_positive(self.adaptation_gain, "controller.adaptation_gain", where)
        _require_positive(self.sample_period_s, "controller.sample_period_s", where)
        if self.sample_period_s > MAX_SAMPLE_PERIOD_S:
            raise ConfigError(
                f"{where}: controller.sample_period_s = {self.sample_period_s:g} s is above "
                f"{MAX_SAMPLE_PERIOD_S:g} s: the piecewise-constant law's filter needs "
                "k w_max T_s <= 1 with filter gains of about 100/s and more (docs/design.md "
                "5.3a); the period is in seconds (1 ms is 0.001)")
        _require_positive(self.projection_epsilon, "controller.projection_epsilon", where)
        _require_positive(self.min_radius_m, "controller.min_radius_m", where)
        for key in ("preview_ahead_s", "preview_window_s"):
            value = getattr(self, key)
            if not (math.isfinite(value) and value >= 0):
                raise ConfigError(f"{where}: controller.{key} = {value!r} must be a finite "
                                  "number >= 0 (s)")
        if self.bound_factor < 1.0:
            raise ConfigError(
                f"{where}: controller.bound_factor = {self.bound_factor} must be >= 1")
        if len(self.q_ad_diag) != 4 or min(self.q_ad_diag) <= 0:
            raise ConfigError(f"{where}: controller.q_ad_diag = {self.q_ad_diag} must be four "
                              "positive numbers")


@dataclasses.dataclass
class SynthesisSettings:
    """Gain LMI and safe-speed search settings (DESIGN section 5)."""

    decay_rate: float = 0.2  # alpha (1/s): A_cl + alpha I Hurwitz at every corner
    lmi_margin: float = 1.0e-6  # eps of the strict LMI (normalised by X >= I)
    speed_min_mps: float = _plausible(5.0, SPEED_PLAUSIBLE)
    speed_max_mps: float = _plausible(30.0, SPEED_PLAUSIBLE)
    filter_gain_max: float = 500.0  # k_bar
    design_radius_m: float = 50.0  # road radius for the offset and grip conditions
    # grip (DESIGN 5.3d): admissible tire slip as a normalised slip z = C |tan a| / (3 mu F_z)
    # (Fiala: 1 = the patch slides); the design covers secant stiffness down to
    # C_lo (1 - z + z^2/3) at this bound
    normalised_slip_max: float = 0.6
    lateral_accel_fraction: float = 0.85  # a_y <= fraction * mu_lo * g
    # vehicle limits (DESIGN 5.3e): a_y <= rollover_fraction * g * t / (2 h) for a vehicle
    # that gives its CG height h and track t; a_y <= lateral_accel_limit_mps2 when given
    rollover_fraction: float = dataclasses.field(default=0.7, metadata={"optional": True})
    lateral_accel_limit_mps2: float | None = _plausible(None, Plausible(
        0.5, 15.0, "m/s^2", "a lateral acceleration limit", small=((GRAVITY_MPS2, "g"),)),
        optional=True)
    speed_grid_step_mps: float = 0.5
    stiffness_grid_points: int = 5
    w_grid_points: int = 5

    def validate(self, where: str = "settings") -> None:
        for key in ("decay_rate", "lmi_margin", "filter_gain_max", "design_radius_m",
                    "normalised_slip_max", "lateral_accel_fraction", "speed_grid_step_mps"):
            _require_positive(getattr(self, key), f"synthesis.{key}", where)
        for key in ("normalised_slip_max", "lateral_accel_fraction"):
            if getattr(self, key) >= 1.0:
                raise ConfigError(f"{where}: synthesis.{key} = {getattr(self, key)} must be "
                                  "below 1 (1 is the friction limit)")
        _require_positive(self.speed_min_mps, "synthesis.speed_min_mps", where)
        if not (math.isfinite(self.rollover_fraction) and 0.0 < self.rollover_fraction <= 1.0):
            raise ConfigError(f"{where}: synthesis.rollover_fraction = {self.rollover_fraction!r}"
                              " must be in (0, 1]: the share of the rigid vehicle's rollover "
                              "threshold t g / (2 h) a steady turn may use")
        if self.lateral_accel_limit_mps2 is not None:
            _require_positive(self.lateral_accel_limit_mps2, "synthesis.lateral_accel_limit_mps2",
                              where)
        check_plausible_fields(self, "synthesis.", where)
        if self.speed_min_mps > self.speed_max_mps:
            raise ConfigError(f"{where}: synthesis.speed_min_mps ({self.speed_min_mps}) exceeds "
                              f"synthesis.speed_max_mps ({self.speed_max_mps})")
        for key in ("stiffness_grid_points", "w_grid_points"):
            if getattr(self, key) < 2:
                raise ConfigError(f"{where}: synthesis.{key} = {getattr(self, key)} must be >= 2")


@dataclasses.dataclass
class Settings:
    """Controller and synthesis settings, one file."""

    controller: ControllerSettings = dataclasses.field(default_factory=ControllerSettings)
    synthesis: SynthesisSettings = dataclasses.field(default_factory=SynthesisSettings)

    def validate(self, where: str = "settings") -> None:
        self.controller.validate(where)
        self.synthesis.validate(where)
        if self.controller.min_radius_m > self.synthesis.design_radius_m:
            raise ConfigError(f"{where}: controller.min_radius_m = {self.controller.min_radius_m} "
                              "must not exceed synthesis.design_radius_m = "
                              f"{self.synthesis.design_radius_m} (the sets must cover the design "
                              "curvature)")


# --------------------------------------------------------------------------- label ranges

LABEL_RANGE_SEPARATOR = "+"  # "light_rain+heavy_rain": the one notation printed and parsed


def format_label_range(labels: typing.Iterable[str]) -> str:
    """A label range as printed everywhere (``synthesize``, ``simulate``): "a+b+c"."""
    return LABEL_RANGE_SEPARATOR.join(labels)


def parse_label_range(text: str) -> list[str]:
    """The labels of a range written as :func:`format_label_range` prints it ("a+b").

    A comma is read as "+" too (the notation of earlier versions). Empty names are errors.
    """
    names = [s.strip() for s in text.replace(",", LABEL_RANGE_SEPARATOR).split(
        LABEL_RANGE_SEPARATOR)]
    if not text.strip() or any(not n for n in names):
        raise ConfigError(f"label range {text!r}: expected label names joined by "
                          f"{LABEL_RANGE_SEPARATOR!r}, e.g. 'light_rain+heavy_rain'")
    return names


# --------------------------------------------------------------------------- loading

def _require_positive(value: float, key: str, where: str) -> None:
    if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
        raise ConfigError(f"{where}: {key} = {value!r} must be a positive finite number")


def _check_keys(schema: type, data: typing.Any, path: str, where: str) -> None:
    """Unknown and missing keys, types of numbers and strings, and plausible ranges
    (:class:`Plausible`), recursively against the dataclass schema, on the parsed YAML.

    pydrake's strict mode (``yaml_load_typed(..., allow_schema_with_no_yaml=False)``) is not
    used instead: it cannot leave one key optional (``tire_stiffness_scale``), its messages
    name neither the key's path ("The fields ['decay_rate'] were missing") nor, for a wrong
    type, the key, and this runs before pydrake is imported."""
    if not dataclasses.is_dataclass(schema):
        return
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: {path or 'top level'} must be a mapping, got {data!r}")
    hints = typing.get_type_hints(schema)
    fields = dataclasses.fields(schema)
    names = {f.name for f in fields}
    unknown = sorted(set(data) - names, key=str)
    if unknown:
        raise ConfigError(f"{where}: unknown key {_join(path, str(unknown[0]))!r}; expected one "
                          f"of {', '.join(sorted(names))}")
    missing = [f.name for f in fields if f.name not in data and not f.metadata.get("optional")]
    if missing:
        raise ConfigError(f"{where}: missing key {_join(path, sorted(missing)[0])!r}")
    for field in (f for f in fields if f.name in data):  # in the schema's order: deterministic
        name, hint, sub = field.name, hints[field.name], data[field.name]
        if _optional_number(hint):
            if sub is None:
                continue
            hint = float
        if dataclasses.is_dataclass(hint):
            _check_keys(hint, sub, _join(path, name), where)
        elif hint in (float, int) and (isinstance(sub, bool) or not isinstance(sub, (int, float))):
            raise ConfigError(f"{where}: {_join(path, name)} = {sub!r} must be a number")
        elif "plausible" in field.metadata:
            field.metadata["plausible"].check(sub, _join(path, name), where)
        elif hint is str and not isinstance(sub, str):
            raise ConfigError(f"{where}: {_join(path, name)} = {sub!r} must be a string")
        elif typing.get_origin(hint) is list:
            (item,) = typing.get_args(hint)
            if dataclasses.is_dataclass(item):
                if not isinstance(sub, list):
                    raise ConfigError(f"{where}: {_join(path, name)} must be a list")
                for i, entry in enumerate(sub):
                    _check_keys(item, entry, f"{_join(path, name)}[{i}]", where)


def _optional_number(hint: typing.Any) -> bool:
    """``float | None``: an optional key that is a number when given."""
    return typing.get_origin(hint) in (typing.Union, types.UnionType) \
        and set(typing.get_args(hint)) == {float, type(None)}


def _join(path: str, key: str) -> str:
    return f"{path}.{key}" if path else key


MAX_INPUT_BYTES = 16 * 2**20  # an input file larger than this is refused unread


def read_yaml_text(filename: str | Path, error: type[Exception] = ConfigError) -> str:
    """The text of a YAML file; ``error`` (:class:`ConfigError`) in one line if it cannot be
    read, is larger than ``MAX_INPUT_BYTES`` (read no further: ``/dev/zero`` is refused, not
    read into memory) or is not text (a binary file: the first byte that is not UTF-8 and its
    offset)."""
    try:
        mode = os.stat(filename).st_mode
        if stat.S_ISFIFO(mode) or stat.S_ISSOCK(mode):  # reading would wait for a writer
            raise error(f"{filename}: a named pipe or socket, not a file; give a regular file")
        if stat.S_ISDIR(mode):
            raise error(f"{filename}: a folder, not a file")
        with open(filename, "rb") as f:
            data = f.read(MAX_INPUT_BYTES + 1)
    except OSError as e:
        raise error(f"{filename}: cannot read file ({e.strerror})") from None
    if len(data) > MAX_INPUT_BYTES:
        raise error(f"{filename}: larger than {MAX_INPUT_BYTES // 2**20} MiB; not a "
                    "configuration or design file")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as e:
        raise error(f"{filename}: not a text file (byte {e.object[e.start]:#04x} at offset "
                    f"{e.start} is not UTF-8); expected YAML") from None


class StrictYamlLoader(yaml.SafeLoader):
    """PyYAML's safe loader with two fixes for input files: a key given twice in one mapping
    is an error (PyYAML keeps the last silently), and a number with an exponent but no sign or
    dot (``1.0e12``, ``2e5``) is a float, as in YAML 1.2 (PyYAML's YAML 1.1 reads it as a
    string)."""

    def construct_mapping(self, node, deep=False):
        seen = {}
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=True)
            try:
                line = seen.get(key)
            except TypeError:  # an unhashable key: the base class says so
                break
            if line is not None:
                raise yaml.constructor.ConstructorError(
                    None, None, f"key {key!r} given twice (lines {line} and "
                    f"{key_node.start_mark.line + 1}); give it once", key_node.start_mark)
            seen[key] = key_node.start_mark.line + 1
        return super().construct_mapping(node, deep=deep)


StrictYamlLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$"),
    list("-+0123456789."))


def parse_yaml(text: str, where: str, error: type[Exception] = ConfigError):
    """Parse YAML text with :class:`StrictYamlLoader`; ``error`` in one line naming ``where``."""
    try:
        return yaml.load(text, Loader=StrictYamlLoader)  # noqa: S506 (a SafeLoader subclass)
    except yaml.YAMLError as e:
        raise error(f"{where}: not valid YAML ({' '.join(str(e).split())})") from None


def load_typed(schema: type, filename: str | Path):
    """Load ``filename`` into ``schema`` strictly; :class:`ConfigError` names key and file."""
    where = str(filename)
    text = read_yaml_text(filename)
    raw = parse_yaml(text, where)
    _check_keys(schema, raw, "", where)
    try:
        from pydrake.common.yaml import yaml_load_typed  # once the checks above have passed
    except ImportError:  # torch-only machines (a GPU box training models): no Drake there
        obj = build_without_drake(schema, raw, "", where)
    else:
        try:
            obj = yaml_load_typed(schema=schema, data=text)
        except (RuntimeError, ValueError, TypeError) as e:
            raise ConfigError(f"{where}: {str(e).splitlines()[0]}") from None
    obj.validate(where)
    return obj.with_defaults() if hasattr(obj, "with_defaults") else obj


def build_without_drake(schema: type, data: typing.Any, path: str, where: str):
    """The ``schema`` object of parsed YAML that :func:`_check_keys` has passed, built without
    pydrake (for machines that train models and have torch but not Drake); the same object as
    pydrake's ``yaml_load_typed`` gives for every shipped file (tests/test_config.py)."""
    if dataclasses.is_dataclass(schema):
        hints = typing.get_type_hints(schema)
        return schema(**{k: build_without_drake(hints[k], v, _join(path, k), where)
                         for k, v in data.items()})
    if typing.get_origin(schema) is list:
        (item,) = typing.get_args(schema)
        if not isinstance(data, list):
            raise ConfigError(f"{where}: {path} must be a list")
        return [build_without_drake(item, v, f"{path}[{i}]", where) for i, v in enumerate(data)]
    if _optional_number(schema):
        return None if data is None else build_without_drake(float, data, path, where)
    if schema is float:
        if isinstance(data, bool) or not isinstance(data, int | float):
            raise ConfigError(f"{where}: {path} = {data!r} must be a number")
        return float(data)
    if schema is int:
        if isinstance(data, bool) or not isinstance(data, int):
            raise ConfigError(f"{where}: {path} = {data!r} must be an integer")
        return data
    if schema is str and not isinstance(data, str):
        raise ConfigError(f"{where}: {path} = {data!r} must be a string")
    return data


def load_typed_mapping(schema: type, data: typing.Any, where: str):
    """Like :func:`load_typed` for an already-parsed YAML mapping (e.g. a block of a saved file).

    ``where`` names the source in error messages; raises :class:`ConfigError`.
    """
    _check_keys(schema, data, "", where)
    from pydrake.common.yaml import yaml_load_typed

    try:
        obj = yaml_load_typed(schema=schema, data=yaml.safe_dump(data))
    except (RuntimeError, ValueError, TypeError) as e:
        raise ConfigError(f"{where}: {str(e).splitlines()[0]}") from None
    obj.validate(where)
    return obj.with_defaults() if hasattr(obj, "with_defaults") else obj


def default_path(name: str) -> Path:
    """Path of a default data file shipped in ``drake_cert/data``."""
    return Path(str(resources.files("drake_cert.data") / name))


def load_vehicle(filename: str | Path | None = None) -> VehicleParams:
    return load_typed(VehicleParams, filename or default_path("vehicle.yaml"))


def load_conditions(filename: str | Path | None = None) -> ConditionsTable:
    return load_typed(ConditionsTable, filename or default_path("conditions.yaml"))


def load_settings(filename: str | Path | None = None) -> Settings:
    return load_typed(Settings, filename or default_path("settings.yaml"))
