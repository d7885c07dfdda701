"""Backends that evaluate the base model on batches of noisy frames: torch itself, or ONNX
Runtime on the CPU in float32 or int8.

Whatever module :func:`evaluated_model` returns is the base model of the certificate: the
sampler, the calibration and any attack must all use that same module. ONNX Runtime is an
optional dependency (``pip install 'drake-cert[onnx]'``), imported only when used.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import io
import tempfile
import warnings
from pathlib import Path

import numpy as np
import torch

from drake_cert.certification.statistics import check_sigma
from drake_cert.errors import CertificationError

BACKENDS = ("torch", "onnxruntime")
QUANTIZATIONS = ("none", "int8")
CALIBRATION_SAMPLES = 256  # noisy frames that set the int8 activation ranges
CALIBRATION_BATCH = 32
INSTALL_HINT = "pip install 'drake-cert[onnx]'"


def onnxruntime_available() -> bool:
    """Whether the ``onnx`` extra is installed (onnxruntime, and onnx for the export)."""
    return all(importlib.util.find_spec(name) is not None for name in ("onnxruntime", "onnx"))


def resolve_backend(backend: str, precision: str = "fp32") -> str:
    """``backend`` checked against :data:`BACKENDS`; "auto" means "onnxruntime" when it is
    installed and the (resolved) precision is fp32, else "torch" (bf16 runs in torch)."""
    if backend == "auto":
        return "onnxruntime" if precision == "fp32" and onnxruntime_available() else "torch"
    if backend not in BACKENDS:
        raise CertificationError(f"backend {backend!r} is not one of auto, {', '.join(BACKENDS)}")
    return backend


def check_quantization(quantization: str) -> None:
    """Raise :class:`CertificationError` unless ``quantization`` is one of :data:`QUANTIZATIONS`."""
    if quantization not in QUANTIZATIONS:
        raise CertificationError(f"quantization {quantization!r} is not one of "
                                 f"{', '.join(QUANTIZATIONS)}")


def export_onnx(model: torch.nn.Module, frame_size: int) -> bytes:
    """The eval-mode ``model`` as ONNX bytes, input "z" [B, 3, H, W] with a dynamic batch.

    Uses torch's TorchScript exporter (``dynamo=False``): with torch 2.13 it needs only the
    ``onnx`` package (which int8 quantization needs anyway) and exports the shipped models in
    0.05-0.5 s; the dynamo exporter also works but needs onnxscript and onnx-ir besides and
    takes ~4 s. torch deprecates the TorchScript exporter: if a later torch removes it, switch
    to ``dynamo=True`` with ``dynamic_shapes`` and add onnxscript to the extra. In eval mode it
    folds batch norm into the convolutions.
    """
    buf = io.BytesIO()
    with warnings.catch_warnings():  # the exporter's deprecation notices, not the user's
        warnings.simplefilter("ignore", category=DeprecationWarning)
        warnings.simplefilter("ignore", category=FutureWarning)
        torch.onnx.export(model.eval(), (torch.zeros(1, 3, frame_size, frame_size),), buf,
                          dynamo=False, input_names=["z"], output_names=["out"],
                          dynamic_axes={"z": {0: "batch"}, "out": {0: "batch"}})
    return buf.getvalue()


def quantize_int8(model_bytes: bytes, calibration_frames: torch.Tensor, sigma: float,
                  seed: int) -> bytes:
    """Static int8 quantization of an ONNX model: ONNX Runtime's pre-processing, then QDQ with
    uint8 activations and per-channel int8 weights ("U8S8": 2x the fp32 speed on an
    AVX512-VNNI CPU, where S8S8 was slower than fp32). Activation ranges are the min/max over
    :data:`CALIBRATION_SAMPLES` noisy copies of ``calibration_frames`` (``frame + N(0,
    sigma^2)``, unclipped, as the sampler draws them; noise from
    ``numpy.random.default_rng(seed)``). Same inputs, same bytes."""
    from onnxruntime.quantization import (
        CalibrationDataReader,
        CalibrationMethod,
        QuantFormat,
        QuantType,
        quantize_static,
    )
    from onnxruntime.quantization.shape_inference import quant_pre_process

    frames = calibration_frames.detach().to(torch.float32).cpu().numpy()
    rng = np.random.default_rng(seed)
    idx = np.arange(CALIBRATION_SAMPLES) % len(frames)
    noisy = frames[idx] + rng.normal(0.0, sigma, (CALIBRATION_SAMPLES, *frames.shape[1:]))
    batches = iter(np.split(noisy.astype(np.float32), CALIBRATION_SAMPLES // CALIBRATION_BATCH))

    class Reader(CalibrationDataReader):
        def get_next(self):
            batch = next(batches, None)
            return None if batch is None else {"z": batch}

    with tempfile.TemporaryDirectory(prefix="drake-cert-int8.") as tmp:
        fp32, out = Path(tmp) / "fp32.onnx", Path(tmp) / "int8.onnx"
        fp32.write_bytes(model_bytes)
        quant_pre_process(fp32, fp32)  # shape inference and graph clean-up, in place
        quantize_static(fp32, out, Reader(),
                        quant_format=QuantFormat.QDQ, per_channel=True,
                        activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8,
                        calibrate_method=CalibrationMethod.MinMax)
        return out.read_bytes()


@dataclasses.dataclass(frozen=True)
class Int8Calibration:
    """What int8 quantization (:func:`quantize_int8`) is calibrated on: noisy copies of
    ``frames`` at ``sigma`` drawn from the stream ``seed``."""

    frames: torch.Tensor | None  # clean frames [N, 3, H, W] in [0, 1]
    sigma: float | None  # noise std of the copies (pixel units)
    seed: int = 0


class OnnxRuntimeModel(torch.nn.Module):
    """A torch model evaluated by ONNX Runtime on the CPU: frames [B, 3, H, W] float32 ->
    float32 outputs of the torch model's shape ([B, K] logits, or the regressor's [B, 1] / [B]).

    Built by exporting the eval-mode model (:func:`export_onnx`, in memory) and opening an
    ``InferenceSession`` (CPUExecutionProvider, all graph optimisations, ``threads``
    intra-op threads, default ``torch.get_num_threads()`` at construction, that do not spin
    while waiting for work, one inter-op thread). The outputs do not depend on ``threads``
    (measured bit for bit at 1, 2 and 4 on the robotcar-like sigma-1 classifier; tested on
    carla-like). H = W = ``model.meta["image_size"]`` when the model records it, else
    ``frame_size`` (pixels); other sizes are rejected by the session.

    Not differentiable, and a snapshot: later changes to the torch model's weights are not
    seen. ``torch_model`` is the surrogate a gradient attack must use. In float32 the two agree
    to float rounding (different kernels, ~1e-6 relative), so gradients of ``torch_model`` are
    those of this model. With ``quantization="int8"`` (:func:`quantize_int8`, calibrated on
    noisy copies of ``calibration_frames`` at ``sigma``) the certificate is the certificate of
    the quantized model as evaluated here, and an attack must target that model: gradients of
    the float32 ``torch_model`` are then only a BPDA-style approximation (straight-through the
    rounding), and the attack's success must be judged by this model's outputs.
    """

    def __init__(self, model: torch.nn.Module, *, quantization: str = "none",
                 calibration: Int8Calibration | None = None, threads: int | None = None,
                 frame_size: int = 64):
        super().__init__()
        calibration = calibration or Int8Calibration(None, None)
        calibration_frames, sigma = calibration.frames, calibration.sigma
        seed = calibration.seed
        check_quantization(quantization)
        if quantization == "int8":
            if calibration_frames is None or calibration_frames.dim() != 4 or sigma is None:
                raise CertificationError("int8 quantization needs calibration_frames (clean "
                                         "frames [N, 3, H, W] in [0, 1]) and sigma")
            check_sigma(sigma)
        import onnxruntime as ort

        self.torch_model = model.eval()
        self.quantization = quantization
        if hasattr(model, "meta"):
            self.meta = model.meta
        size = int(getattr(model, "meta", {}).get("image_size", frame_size))
        onnx_bytes = export_onnx(model, size)
        if quantization == "int8":
            onnx_bytes = quantize_int8(onnx_bytes, calibration_frames, sigma, seed)
        options = ort.SessionOptions()
        options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        options.intra_op_num_threads = int(threads or torch.get_num_threads())
        options.inter_op_num_threads = 1
        # Idle intra-op threads block instead of spinning: a spinning pool competes with the
        # Diagram's own thread for the cores between two frames (DESIGN 3.8).
        options.add_session_config_entry("session.intra_op.allow_spinning", "0")
        self.threads = options.intra_op_num_threads
        self.session = ort.InferenceSession(onnx_bytes, options,
                                            providers=["CPUExecutionProvider"])

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        """Outputs on a float32 CPU batch (no copy when it is contiguous float32)."""
        z = z.detach().to(device="cpu", dtype=torch.float32).contiguous()
        try:
            (out,) = self.session.run(None, {"z": z.numpy()})
        except Exception as e:  # noqa: BLE001 - ORT's errors are plain Exceptions
            raise RuntimeError(str(e)) from e  # torch's type, which the sampler reports
        return torch.from_numpy(out)


def evaluated_model(model: torch.nn.Module, *, backend: str = "torch", quantization: str = "none",
                    precision: str = "fp32", calibration: Int8Calibration | None = None,
                    threads: int | None = None) -> torch.nn.Module:
    """The module the sampler should call for ``model`` (eval mode).

    backend "torch": ``model`` itself (bf16 is applied elsewhere, by ``with_precision``;
    int8 is not offered). "onnxruntime": an :class:`OnnxRuntimeModel` (fp32 only), int8 when
    ``quantization="int8"``, which needs ``calibration`` (:class:`Int8Calibration`: the
    calibration frames, sigma and seed). "auto" resolves
    by :func:`resolve_backend`. Raises :class:`CertificationError` on unknown names, on
    bf16 or int8 combinations that do not exist, and when onnxruntime is not installed.
    """
    backend = resolve_backend(backend, precision)
    check_quantization(quantization)
    if backend == "torch":
        if quantization != "none":
            raise CertificationError(f"quantization {quantization!r} needs backend onnxruntime")
        return model.eval()
    if precision != "fp32":
        raise CertificationError(f"backend onnxruntime evaluates in fp32 (or int8), not "
                                 f"precision {precision!r}")
    if not onnxruntime_available():
        raise CertificationError(f"backend onnxruntime is not installed: {INSTALL_HINT}")
    return OnnxRuntimeModel(model, quantization=quantization, calibration=calibration,
                            threads=threads)
