"""The noisy sampler: a base model evaluated on Gaussian-noised copies of one frame (the hot
path of both smoothed models), the frame and device checks, and seeded generators.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable, Iterator, Sequence

import torch

from drake_cert.certification.statistics import check_count, check_sigma
from drake_cert.errors import CertificationError


def check_frame(x: torch.Tensor) -> None:
    """Raise :class:`CertificationError` unless x is one finite float [C, H, W] frame in [0, 1]."""
    if not isinstance(x, torch.Tensor):
        raise CertificationError(f"frame must be a torch.Tensor, got {type(x).__name__}")
    if x.dim() != 3 or min(x.shape) == 0:
        raise CertificationError(f"frame must have shape [C, H, W], got {list(x.shape)}")
    if not x.is_floating_point():
        raise CertificationError(f"frame dtype must be floating point in [0, 1], got {x.dtype} "
                                 "(convert uint8 images with x.float() / 255)")
    if not torch.isfinite(x).all():
        raise CertificationError("frame contains NaN or infinite values")
    lo, hi = float(x.min()), float(x.max())
    if lo < -1e-6 or hi > 1 + 1e-6:
        raise CertificationError(f"frame values must lie in [0, 1], got [{lo:.4g}, {hi:.4g}]")


def resolve_device(device: str | torch.device) -> torch.device:
    """``torch.device`` for ``device``; CUDA only when asked for and available."""
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError) as e:
        raise CertificationError(f"unknown device {device!r} ({e})") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise CertificationError(f"device {device!r} requested but CUDA is not available")
    return dev




class NoisySampler:
    """Evaluates a base model on Gaussian-noised copies of one frame: the hot path.

    One preallocated [batch_size, C, H, W] buffer per shape; noise is written into it in place
    (``normal_``), the frame is added in place, and the model runs under
    ``torch.inference_mode``. With a compiled model every batch has the same shape (the last
    one is padded and its extra outputs dropped), so it is compiled once; an eager model runs
    a short last batch unpadded.
    """

    def __init__(self, base: torch.nn.Module, sigma: float, device: str | torch.device,
                 compile: bool):
        check_sigma(sigma)
        if not isinstance(base, torch.nn.Module):
            raise CertificationError(f"base model must be a torch.nn.Module, got "
                                     f"{type(base).__name__}")
        self.sigma = float(sigma)
        self.device = resolve_device(device)
        self.base = base.to(self.device).eval()
        self.compiled = False
        self.compile_seconds = 0.0
        self._model: Callable[[torch.Tensor], torch.Tensor] = self.base
        self._needs_first_call = False
        if compile:
            try:
                # Freezing folds batch norm into the convolutions and pre-packs weights for
                # inference (2x over plain compilation on CPU, measured); the weights are then
                # constants, so build a new smoothed model after changing the base model.
                self._model = torch.compile(self.base, dynamic=False,
                                            options={"freezing": True})
                self.compiled = True
                self._needs_first_call = True
            except Exception as e:  # noqa: BLE001 - any failure means: run eager
                warnings.warn(f"torch.compile unavailable ({e}); running the model eagerly",
                              RuntimeWarning, stacklevel=3)
        self._buffer: torch.Tensor | None = None

    def _forward(self, batch: torch.Tensor) -> torch.Tensor:
        if not self._needs_first_call:
            return self._model(batch)
        # The first call compiles; a failure (no C++ compiler, unsupported op) falls back.
        start = time.perf_counter()
        try:
            out = self._model(batch)
        except Exception as e:  # noqa: BLE001
            warnings.warn(f"torch.compile failed ({type(e).__name__}: {str(e)[:200]}); "
                          "running the model eagerly", RuntimeWarning, stacklevel=4)
            self._model, self.compiled = self.base, False
            out = self._model(batch)
        self.compile_seconds += time.perf_counter() - start
        self._needs_first_call = False
        return out

    def _get_buffer(self, shape: torch.Size, batch_size: int, dtype: torch.dtype) -> torch.Tensor:
        want = (batch_size, *shape)
        if self._buffer is None or tuple(self._buffer.shape) != want or self._buffer.dtype != dtype:
            if self.compiled and self._buffer is not None:
                self._needs_first_call = True  # a new shape recompiles: time it separately
            self._buffer = torch.empty(want, dtype=dtype, device=self.device)
        return self._buffer

    def outputs(self, x: torch.Tensor, num: int, batch_size: int,
                generator: torch.Generator | None,
                selection: bool = False) -> Iterator[torch.Tensor]:
        """Yield the model's outputs on ``num`` noisy copies of ``x``, batch by batch.

        ``selection``: the samples only choose a label (CERTIFY's n0), which no guarantee
        depends on; a short batch then runs the eager model unpadded (cheaper than a padded
        compiled batch when it is at most half full). Estimation samples always use one model
        (the compiled one when compiled, padding the last batch).
        Must be consumed inside ``torch.inference_mode()`` (the callers do).
        """
        check_count(num, "number of samples")
        check_count(batch_size, "batch_size")
        check_frame(x)
        x = x.to(device=self.device, dtype=torch.float32)
        buf = self._get_buffer(x.shape, batch_size, torch.float32)
        remaining = num
        while remaining > 0:
            m = min(batch_size, remaining)
            # Short batches: an eager model runs them unpadded; a compiled one is padded (one
            # shape, compiled once) except for selection samples (see above).
            short = m < batch_size and (not self.compiled or (selection and 2 * m <= batch_size))
            batch = buf[:m] if short else buf
            batch.normal_(0.0, self.sigma, generator=generator)
            batch.add_(x)
            try:
                out = self.base(batch) if short else self._forward(batch)
            except RuntimeError as e:
                raise CertificationError(f"base model rejected a batch of frames of shape "
                                         f"{list(x.shape)}: {str(e).splitlines()[0]}") from None
            yield out[:m]
            remaining -= m

    def warmup(self, frame_shape: Sequence[int], batch_size: int) -> float:
        """Run one batch of the given frame shape (compiling if asked); return its seconds."""
        start = time.perf_counter()
        with torch.inference_mode():
            x = torch.full(tuple(frame_shape), 0.5)
            for _ in self.outputs(x, 1, batch_size, None):
                pass
        return time.perf_counter() - start


def make_generator(seed: int | None, device: torch.device) -> torch.Generator | None:
    """A seeded ``torch.Generator`` on ``device``, or None (global RNG, fresh noise)."""
    if seed is None:
        return None
    return torch.Generator(device=device).manual_seed(int(seed))



class SmoothedModel:
    """What both smoothed models share: the noisy sampler, its device, compilation and warm-up."""

    def __init__(self, base: torch.nn.Module, sigma: float, device: str | torch.device,
                 compile: bool):
        self._sampler = NoisySampler(base, sigma, device, compile)
        self.sigma = self._sampler.sigma
        self.device = self._sampler.device

    @property
    def compile_seconds(self) -> float:
        """Seconds spent in first (compiling) calls so far; 0.0 when not compiled."""
        return self._sampler.compile_seconds if self._sampler.compiled else 0.0

    def warmup(self, frame_shape: Sequence[int], batch_size: int) -> float:
        """Evaluate one batch (compiles the model when asked); returns the seconds taken."""
        return self._sampler.warmup(frame_shape, batch_size)
