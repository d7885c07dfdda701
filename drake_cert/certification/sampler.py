"""The noisy sampler: a base model evaluated on Gaussian-noised copies of one frame (the hot
path of both smoothed models), the frame and device checks, and seeded generators.
"""

from __future__ import annotations

import collections
import concurrent.futures
import copy
import ctypes
import ctypes.util
import dataclasses
import functools
import os
import sys
import time
import warnings
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

import torch

from drake_cert.certification.statistics import check_count, check_sigma
from drake_cert.errors import CertificationError
from drake_cert.rng import torch_generator


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


def check_frame_size(x: torch.Tensor, model: torch.nn.Module) -> None:
    """Raise :class:`CertificationError` when a model that records its training frame size
    (``model.meta["image_size"]``, set by ``load_model``) is given a frame of another size:
    the network's global pooling would accept it and answer about a different picture."""
    size = getattr(model, "meta", {}).get("image_size") if hasattr(model, "meta") else None
    if size is not None and tuple(x.shape[-2:]) != (int(size), int(size)):
        raise CertificationError(f"frame is {x.shape[-2]}x{x.shape[-1]} pixels but the model "
                                 f"was trained on {size}x{size} frames")


def resolve_device(device: str | torch.device) -> torch.device:
    """``torch.device`` for ``device``; CUDA only when asked for and available."""
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError) as e:
        raise CertificationError(f"unknown device {device!r} ({e})") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise CertificationError(f"device {device!r} requested but CUDA is not available")
    return dev




@functools.cache
def retain_freed_memory() -> bool:
    """Ask glibc to keep freed memory for reuse instead of returning it to the kernel.

    With glibc's defaults every batch of noisy copies frees tens of MB of activations, glibc
    trims them off the heap, and the next batch page-faults them back in: a quarter of a
    reproduce worker's CPU time was spent in the kernel. Never trimming (M_TRIM_THRESHOLD) and
    serving blocks up to 32 MB from the heap (M_MMAP_THRESHOLD, glibc's largest) leaves 0
    faults after warm-up; ``benchmarks/bench_sampler_memory.py`` measures both policies side
    by side (batches of 250, one thread: 1.34x samples/s in bf16, 1.74x in fp32), at the cost
    of holding the peak (about 0.8 GB per process). Allocation policy only: no number changes
    (the benchmark checks the outputs). Process-wide and not undone, so nothing calls it
    implicitly (importing this module or building a sampler leaves the allocator alone, e.g.
    in a notebook kernel): the long-running entry points do, explicitly (the ``certify``,
    ``drive`` and ``reproduce`` commands, ``drive --compare``'s worker processes, Ray workers).
    Once per process; True if glibc accepted both settings, False (nothing done) off glibc.
    """
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    m_trim_threshold, m_mmap_threshold = -1, -3  # glibc's malloc.h
    return bool(mallopt(m_trim_threshold, 2**31 - 1)) and bool(mallopt(m_mmap_threshold, 2**25))


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
        self._ahead: _NoiseAhead | None = None
        self._worker: concurrent.futures.ThreadPoolExecutor | None = None

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
        check_frame_size(x, self.base)
        x = x.to(device=self.device, dtype=torch.float32)
        buf = self._get_buffer(x.shape, batch_size, torch.float32)
        remaining = num
        while remaining > 0:
            m = min(batch_size, remaining)
            # Short batches: an eager model runs them unpadded; a compiled one is padded (one
            # shape, compiled once) except for selection samples (see above).
            short = m < batch_size and (not self.compiled or (selection and 2 * m <= batch_size))
            batch = self._queued_noise(generator, m, tuple(x.shape))
            if batch is None:
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

    def draw_ahead(self, seed: int, frame_shape: Sequence[int], batches: Sequence[int]) -> None:
        """Start drawing, on a worker thread, the noise of the first ``batches`` (their sizes,
        in order) of the stream ``seed`` for frames of ``frame_shape``: the next
        :meth:`stream` of that seed hands them to :meth:`outputs`, which would otherwise draw
        them itself. No number changes (the blocks are the ones ``outputs`` would draw, in the
        same order from the same generator); only the time moves, e.g. onto a core the
        simulation leaves idle between two camera frames. Replaces any noise drawn ahead
        before. A compiled model pads its batches, so it draws its own noise (nothing done).
        """
        if self.compiled or seed is None:
            return
        if self._worker is None:
            self._worker = concurrent.futures.ThreadPoolExecutor(
                max_workers=1, thread_name_prefix="drake-cert-noise")
        shape, sigma = tuple(int(d) for d in frame_shape), self.sigma
        sizes = [int(m) for m in batches]
        generator = make_generator(int(seed), self.device)

        def draw() -> collections.deque:
            return collections.deque(
                torch.empty((m, *shape), device=self.device).normal_(0.0, sigma,
                                                                      generator=generator)
                for m in sizes)

        self._ahead = _NoiseAhead(int(seed), generator, self._worker.submit(draw))

    def stream(self, seed: int | None) -> torch.Generator | None:
        """The generator of the noise stream ``seed`` (:func:`make_generator`): the one
        :meth:`draw_ahead` started for this seed, its drawn blocks queued for
        :meth:`outputs` (waiting for the worker if it is still drawing), else a new one."""
        ahead, self._ahead = self._ahead, None
        if ahead is None or seed is None or int(seed) != ahead.seed:
            return make_generator(seed, self.device)
        ahead.queue = ahead.drawing.result()
        self._ahead = ahead
        return ahead.generator

    def _queued_noise(self, generator, m: int, frame_shape: tuple) -> torch.Tensor | None:
        """The next block drawn ahead for ``generator`` (None when there is none: the batch
        draws its own noise). It must be the ``m`` noisy copies of a ``frame_shape`` frame this
        batch would draw: any other block would put the stream out of order, a bug raised as
        such."""
        ahead = self._ahead
        if ahead is None or generator is None or generator is not ahead.generator \
                or not ahead.queue:
            return None
        block = ahead.queue.popleft()
        if tuple(block.shape) != (m, *frame_shape):
            raise RuntimeError(f"noise drawn ahead as a block of shape {list(block.shape)}, "
                               f"but the batch draws {[m, *frame_shape]}")
        return block

    def warmup(self, frame_shape: Sequence[int], batch_size: int) -> float:
        """Run one batch of the given frame shape (compiling if asked); return its seconds."""
        start = time.perf_counter()
        with torch.inference_mode():
            x = torch.full(tuple(frame_shape), 0.5)
            for _ in self.outputs(x, 1, batch_size, None):
                pass
        return time.perf_counter() - start


@dataclasses.dataclass
class _NoiseAhead:
    """Noise of one stream being drawn ahead (:meth:`NoisySampler.draw_ahead`)."""

    seed: int
    generator: torch.Generator
    drawing: concurrent.futures.Future  # the worker's deque of blocks
    queue: collections.deque | None = None  # the blocks, once handed over by ``stream``


@dataclasses.dataclass(frozen=True)
class CalibrationSampling:
    """How the calibration frames are sampled (DESIGN 3): n noisy samples per frame, drawn
    in batches, from seeded noise streams, with an optional progress wrapper.

    ``seed`` is the root of the noise: the classifier's calibration
    (:func:`~drake_cert.certification.conformal.true_label_counts`) draws frame i from
    ``seeds.stream_seed(seed, i, "calibration", split="calibration")``; the regressor's
    (:func:`~drake_cert.certification.regressor.calibrate_conformal`) draws every frame from
    one stream of ``seed``, or frame i from ``frame_seeds[i]`` when they are given. None:
    fresh global noise.
    """

    n: int  # noisy samples per calibration frame
    batch_size: int  # most noisy copies per forward pass
    seed: int | None = 0  # root of the noise streams (see above)
    progress: Callable | None = None  # wraps the iterator over frame indices (a bar)
    frame_seeds: Sequence[int] | None = None  # regressor only: one stream per frame


def make_generator(seed: int | None, device: torch.device) -> torch.Generator | None:
    """A ``torch.Generator`` on ``device`` whose state depends on every bit of ``seed``
    (:func:`drake_cert.rng.torch_generator`), or None (global RNG, fresh
    noise)."""
    if seed is None:
        return None
    return torch_generator(int(seed), device)



PRECISIONS = ("fp32", "bf16")
"""Arithmetic a base model can be evaluated in."""
PRECISION_SETTINGS = ("auto", *PRECISIONS)
"""What a setting may say: ``auto`` is resolved by :func:`resolve_precision`."""
PRECISION_ENV = "DRAKE_CERT_PRECISION"
"""Environment variable that fixes what ``auto`` means for a whole process (fp32 or bf16)."""


class Bfloat16Model(torch.nn.Module):
    """The base model evaluated in bfloat16: ``f'(z) = f_bf16(round_bf16(z))``, as float32.

    A copy of the base model in bfloat16 with channels-last weights. The rounding of the noisy
    frame to bfloat16 is part of this base model, so the Gaussian noise is still drawn and
    added in float32, as the certificates assume; they are certificates of ``f'`` (not of the
    float32 model), so attacks, calibration and certification must all use this same module
    (:func:`with_precision`). ~1.5-1.8x faster than float32 on CPUs with AVX512-BF16/AMX, and
    ~8x slower where bfloat16 is emulated (AVX2 only): ``auto`` picks it only where native.
    """

    def __init__(self, base: torch.nn.Module):
        super().__init__()
        self.net = copy.deepcopy(base).to(torch.bfloat16).to(memory_format=torch.channels_last)
        if hasattr(base, "meta"):
            self.meta = base.meta

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        z = z.to(torch.bfloat16)
        if z.dim() == 4:
            z = z.contiguous(memory_format=torch.channels_last)
        return self.net(z).float()


def bf16_supported() -> bool:
    """Whether this CPU has native bfloat16 arithmetic (AVX512-BF16 or AMX-BF16 in
    /proc/cpuinfo); elsewhere bfloat16 is emulated and slower than float32."""
    try:
        flags = Path("/proc/cpuinfo").read_text()
    except OSError:
        return False
    return "avx512_bf16" in flags or "amx_bf16" in flags


def resolve_precision(precision: str = "auto") -> str:
    """The arithmetic a setting means on this machine: "fp32" or "bf16".

    "fp32" and "bf16" mean themselves. "auto" (the default everywhere) means the value of the
    environment variable ``DRAKE_CERT_PRECISION`` when it is set, else the fastest sound
    evaluation by a rule measured on both kinds of CPU (DESIGN 3.8): fp32 where ONNX Runtime
    is installed (its fp32 session beat torch bf16 on CPUs with native bfloat16: 3,400 against
    2,100-2,300 samples per CPU-second on an AMD EPYC with avx512_bf16; a drive at 0.90x
    against 0.58x real time on an Intel Xeon with avx512_bf16), else "bf16" where
    :func:`bf16_supported` (torch bf16 against torch fp32) and "fp32" elsewhere. Certificates
    are those of the model as evaluated, so record what this returns beside every result.
    Raises :class:`CertificationError` for any other value.
    """
    if precision not in PRECISION_SETTINGS:
        raise CertificationError(f"precision {precision!r} is not one of "
                                 f"{', '.join(PRECISION_SETTINGS)}")
    if precision != "auto":
        return precision
    forced = os.environ.get(PRECISION_ENV, "").strip()
    if forced:
        if forced not in PRECISIONS:
            raise CertificationError(f"{PRECISION_ENV}={forced!r} must be one of "
                                     f"{', '.join(PRECISIONS)} (or unset)")
        return forced
    from drake_cert.certification.backends import onnxruntime_available

    if onnxruntime_available():
        return "fp32"
    return "bf16" if bf16_supported() else "fp32"


def with_precision(model: torch.nn.Module, precision: str) -> torch.nn.Module:
    """``model`` itself (fp32) or its :class:`Bfloat16Model` (bf16), in eval mode; "auto" is
    resolved by :func:`resolve_precision`."""
    if resolve_precision(precision) == "fp32" or isinstance(model, Bfloat16Model):
        return model
    return Bfloat16Model(model).eval()


class SmoothedModel:
    """What both smoothed models share: the noisy sampler, its device, compilation and warm-up."""

    def __init__(self, base: torch.nn.Module, sigma: float, device: str | torch.device,
                 compile: bool, precision: str = "fp32"):
        if not isinstance(base, torch.nn.Module):
            raise CertificationError(f"base model must be a torch.nn.Module, got "
                                     f"{type(base).__name__}")
        self.precision = resolve_precision(precision)
        self._sampler = NoisySampler(with_precision(base, self.precision), sigma, device,
                                     compile)
        self.sigma = self._sampler.sigma
        self.device = self._sampler.device

    @property
    def compile_seconds(self) -> float:
        """Seconds spent in first (compiling) calls so far; 0.0 when not compiled."""
        return self._sampler.compile_seconds if self._sampler.compiled else 0.0

    def warmup(self, frame_shape: Sequence[int], batch_size: int) -> float:
        """Evaluate one batch (compiles the model when asked); returns the seconds taken."""
        return self._sampler.warmup(frame_shape, batch_size)

    def draw_ahead(self, seed: int, frame_shape: Sequence[int], batches: Sequence[int]) -> None:
        """Draw the first ``batches`` of the noise stream ``seed`` on a worker thread
        (:meth:`NoisySampler.draw_ahead`: the same numbers, earlier)."""
        self._sampler.draw_ahead(seed, frame_shape, batches)

    def stream(self, seed: int | None) -> torch.Generator | None:
        """The generator of the noise stream ``seed``, with any noise drawn ahead for it
        (:meth:`NoisySampler.stream`)."""
        return self._sampler.stream(seed)
