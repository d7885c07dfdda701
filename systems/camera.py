"""The forward camera: a frame of the road a look-ahead distance ahead, at the camera rate.

At each tick k (``t_k = k / rate_hz``, a periodic unrestricted update at offset 0) the
camera reads the car's arc length s, looks at the route point ``p = s + look_ahead_m`` and
renders one frame of that point's segment: the procedural generator of the perception preset
(``drake_cert.perception.frames.render_frames``) draws the segment's condition with the
severity of the segment's TRUE stiffness (``severity_from_stiffness``), from the random stream
``camera`` (k) of the seed (:mod:`drake_cert.certification.seeds`). With ``frames_dir`` a user's
class-per-folder image of the segment's condition is drawn from the same stream instead. The
frame and its truth (label, stiffness, friction of the seen segment) are held in abstract state
until the next tick.
"""

import dataclasses
import math

import torch
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import BasicVector, EventStatus, LeafSystem

from drake_cert.certification.seeds import Purpose, child_rng, child_seed
from drake_cert.config import ConditionsTable
from drake_cert.errors import ConfigError
from drake_cert.perception.datasets import load_image_folder
from drake_cert.perception.frames import (
    CAMERA_CONTRAST,
    render_frames,
    severity_from_stiffness,
    style_for,
)
from drake_cert.rng import torch_generator
from drake_cert.systems.route import Route
from drake_cert.systems.scenario import CameraSettings


@dataclasses.dataclass(frozen=True)
class CameraFrame:
    """One camera frame and the truth of the road it shows.

    ``image``: float32 [3, H, W] in [0, 1] (NaN or another shape under fault attacks).
    """

    image: torch.Tensor
    time_s: float  # capture time (s)
    tick: int  # camera tick k (t = k / rate_hz); -1 for the placeholder
    position_m: float  # arc length of the look-ahead point the frame shows (m)
    label_index: int  # true condition of the seen segment (preset label order)
    stiffness_n_per_rad: float  # true cornering stiffness per tire of the seen segment
    friction_mu: float  # true friction coefficient of the seen segment
    attack: str = "none"  # what the attacker did to the image ("none", "sa", "ea", "nan", ...)
    perturbation_l2: float = 0.0  # L2 norm of the attacker's change (pixel units; NaN faults)

    @staticmethod
    def placeholder(frame_size: int = 64) -> "CameraFrame":
        """A grey frame with no truth (model value of frame ports)."""
        return CameraFrame(torch.full((3, frame_size, frame_size), 0.5), -1.0, -1, 0.0, -1,
                           math.nan, math.nan)


@dataclasses.dataclass(frozen=True)
class CameraSetup:
    """What :class:`CameraSource` needs, checked and precomputed by :func:`camera_setup`."""

    rate_hz: float  # frames per second
    look_ahead_m: float  # the frame shows the road this far ahead (m)
    frame_size: int  # frames are frame_size x frame_size RGB pixels
    seed: int  # root of the camera's random stream
    conditions: dict  # label name -> Condition of the preset
    contrast: float  # the preset's camera contrast
    folder: object = None  # the user's class-per-folder images (a FrameSet), or None


def camera_setup(route: Route, conditions: ConditionsTable, preset: str,
                 camera: CameraSettings, seed: int) -> CameraSetup:
    """Check ``camera`` and load what the camera draws from: ConfigError for a rate or
    look-ahead out of range, or a ``frames_dir`` without images of a route condition."""
    rate_hz, look_ahead_m = camera.rate_hz, camera.look_ahead_m
    if not (math.isfinite(rate_hz) and rate_hz > 0):
        raise ConfigError(f"camera: rate_hz = {rate_hz!r} must be positive")
    if not (math.isfinite(look_ahead_m) and look_ahead_m >= 0):
        raise ConfigError(f"camera: look_ahead_m = {look_ahead_m!r} must be >= 0")
    frame_size, frames_dir = int(camera.frame_size), camera.frames_dir
    labels = list(conditions.preset(preset).labels)
    folder = None
    if frames_dir:
        folder = load_image_folder(frames_dir, preset=preset, size=frame_size,
                                   conditions=conditions)
        for seg in route.segments:
            if not bool((folder.labels == seg.label_index).any()):
                raise ConfigError(f"camera: {frames_dir!r} has no images of "
                                  f"{seg.condition!r}, a condition of the route")
    return CameraSetup(float(rate_hz), float(look_ahead_m), frame_size, int(seed),
                       {name: conditions.condition(name) for name in labels},
                       CAMERA_CONTRAST.get(preset, 1.0), folder)


class CameraSource(LeafSystem):
    """Camera at ``camera.rate_hz`` looking ``camera.look_ahead_m`` ahead along the route.

    ``camera``: a :class:`~drake_cert.systems.scenario.CameraSettings` (default: its
    defaults, 10 Hz, 40 m, 64 px, rendered frames); ``seed``: root of the camera stream.
    Input ``arc_length_m`` (1, m). Outputs ``frame`` (abstract :class:`CameraFrame`, the
    state), ``seen_stiffness_n_per_rad`` (1, N/rad) and ``seen_label_index`` (1) of the seen
    segment (truth, for logs). The state before the first tick is the frame of the route
    point ``look_ahead_m`` from the start at tick 0 (identical to the tick-0 frame of a car
    starting at s = 0).
    """

    def __init__(self, route: Route, conditions: ConditionsTable, preset: str,
                 camera: CameraSettings | None = None, *, seed: int = 0):
        super().__init__()
        setup = camera_setup(route, conditions, preset, camera or CameraSettings(), seed)
        self.route, self.preset = route, preset
        self.rate_hz, self.period_s = setup.rate_hz, 1.0 / setup.rate_hz
        self.look_ahead_m, self.frame_size, self.seed = (setup.look_ahead_m, setup.frame_size,
                                                         setup.seed)
        self._conditions, self._contrast = setup.conditions, setup.contrast
        self._folder = setup.folder
        self._s = self.DeclareVectorInputPort("arc_length_m", 1)
        initial = self.capture(0.0, 0.0, 0)
        state_index = self.DeclareAbstractState(AbstractValue.Make(initial))
        self.DeclarePeriodicUnrestrictedUpdateEvent(self.period_s, 0.0, self._update)
        state = {self.abstract_state_ticket(state_index)}
        self.DeclareAbstractOutputPort("frame", lambda: AbstractValue.Make(initial),
                                       self._calc_frame, prerequisites_of_calc=state)
        self.DeclareVectorOutputPort("seen_stiffness_n_per_rad", 1, self._calc_stiffness,
                                     prerequisites_of_calc=state)
        self.DeclareVectorOutputPort("seen_label_index", 1, self._calc_label,
                                     prerequisites_of_calc=state)

    def capture(self, time_s: float, arc_length_m: float, tick: int) -> CameraFrame:
        """The frame of tick ``tick`` for a car at ``arc_length_m`` (pure: deterministic)."""
        position = float(arc_length_m) + self.look_ahead_m
        seg = self.route.segment_at(position)
        if self._folder is not None:
            image = self._folder_image(seg.label_index, tick)
        else:
            cond = self._conditions[seg.condition]
            severity = severity_from_stiffness(
                torch.tensor([seg.stiffness_n_per_rad], dtype=torch.float64), *cond.interval)
            gen = torch_generator(child_seed(self.seed, Purpose.CAMERA, tick))
            image = render_frames(style_for(seg.condition), severity.float(), generator=gen,
                                  size=self.frame_size, contrast=self._contrast)[0]
        return CameraFrame(image=image, time_s=float(time_s), tick=int(tick),
                           position_m=position, label_index=seg.label_index,
                           stiffness_n_per_rad=seg.stiffness_n_per_rad,
                           friction_mu=seg.friction_mu)

    def _folder_image(self, label_index: int, tick: int) -> torch.Tensor:
        candidates = torch.nonzero(self._folder.labels == label_index).flatten()
        rng = child_rng(self.seed, Purpose.CAMERA, tick)
        return self._folder.images[int(candidates[rng.integers(len(candidates))])].clone()

    def tick_of(self, time_s: float) -> int:
        """Camera tick at time t: ``round(t * rate_hz)``."""
        return int(round(time_s * self.rate_hz))

    def _update(self, context, state) -> EventStatus:
        t = context.get_time()
        frame = self.capture(t, float(self._s.Eval(context)[0]), self.tick_of(t))
        state.get_mutable_abstract_state(0).set_value(frame)
        return EventStatus.Succeeded()

    def _frame(self, context) -> CameraFrame:
        return context.get_abstract_state(0).get_value()

    def _calc_frame(self, context, output: AbstractValue) -> None:
        output.set_value(self._frame(context))

    def _calc_stiffness(self, context, output: BasicVector) -> None:
        output.SetAtIndex(0, self._frame(context).stiffness_n_per_rad)

    def _calc_label(self, context, output: BasicVector) -> None:
        output.SetAtIndex(0, float(self._frame(context).label_index))
