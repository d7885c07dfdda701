"""ONNX Runtime backends for the base model: fp32 is the torch model up to float rounding, int8
is a deterministic model of its own that mostly agrees; bad combinations are refused."""

import subprocess
import sys
import tempfile
from pathlib import Path

import pytest
import torch

from drake_cert.certification.backends import (
    BACKENDS,
    Int8Calibration,
    evaluated_model,
    onnxruntime_available,
    resolve_backend,
)
from drake_cert.certification.classifier import SmoothedClassifier
from drake_cert.errors import CertificationError
from drake_cert.perception.datasets import load_split
from drake_cert.perception.models import load_model

SIGMA = 0.25


@pytest.fixture(scope="module")
def model():
    return load_model("carla-like", "classify", SIGMA)


@pytest.fixture(scope="module")
def calibration_frames():
    return load_split("carla-like", "calibration", frames_per_class=8).images


@pytest.fixture(scope="module")
def noisy():
    """300 noisy copies of 30 test frames (10 per label), as the sampler draws them."""
    frames = load_split("carla-like", "test", frames_per_class=10).images.repeat(10, 1, 1, 1)
    return frames + SIGMA * torch.randn(frames.shape, generator=torch.Generator().manual_seed(0))


@pytest.fixture(scope="module")
def ort_fp32(model):
    pytest.importorskip("onnxruntime")
    return evaluated_model(model, backend="onnxruntime")


@pytest.fixture(scope="module")
def ort_int8(model, calibration_frames):
    pytest.importorskip("onnxruntime")
    return evaluated_model(model, backend="onnxruntime", quantization="int8",
                           calibration=Int8Calibration(calibration_frames, SIGMA))


def test_ort_fp32_is_the_torch_model_up_to_rounding(model, ort_fp32, noisy):
    with torch.inference_mode():
        ref, out = model(noisy), ort_fp32(noisy)
    assert torch.equal(out.argmax(1), ref.argmax(1))
    assert (out - ref).abs().max() <= 1e-3 * ref.abs().max()
    assert ort_fp32.torch_model is model and ort_fp32.meta is model.meta


def test_outputs_are_what_the_sampler_expects(model, ort_fp32):
    for batch in (1, 7):
        out = ort_fp32(torch.rand(batch, 3, 64, 64))
        assert out.dtype == torch.float32 and out.shape == (batch, 3)
    # Through the sampler (full and short batches), the same noise gives the same counts.
    x = load_split("carla-like", "test", frames_per_class=1).images[2]
    counts = [SmoothedClassifier(base, 3, SIGMA, precision="fp32").sample_counts(
        x, 250, 100, torch.Generator().manual_seed(3)) for base in (model, ort_fp32)]
    assert (counts[0] == counts[1]).all() and counts[0].sum() == 250
    assert ort_fp32.session.get_session_options().intra_op_num_threads == 1  # conftest's


def test_ort_outputs_do_not_depend_on_the_thread_count(model, ort_fp32, noisy):
    # The drive runs the session on every available core (DESIGN 3.8), the reproduction's
    # workers on one: the votes, and so every certificate, must be the same bits.
    two = evaluated_model(model, backend="onnxruntime", threads=2)
    assert two.session.get_session_options().intra_op_num_threads == 2
    with torch.inference_mode():
        for batch in (noisy[:1], noisy[:7], noisy):
            assert torch.equal(two(batch), ort_fp32(batch))


def test_regressor_output_shape_is_kept():
    pytest.importorskip("onnxruntime")
    regressor = load_model("carla-like", "regress", SIGMA)
    z = torch.rand(5, 3, 64, 64)
    with torch.inference_mode():
        ref, out = regressor(z), evaluated_model(regressor, backend="onnxruntime")(z)
    assert out.shape == ref.shape and torch.allclose(out, ref, rtol=1e-4, atol=1e-3)


def test_int8_agrees_with_fp32_on_most_noisy_frames(model, ort_int8, noisy):
    with torch.inference_mode():
        agree = (ort_int8(noisy).argmax(1) == model(noisy).argmax(1)).float().mean()
    assert agree >= 0.97  # measured 0.997 (299 of 300)


def test_int8_quantization_is_deterministic(model, calibration_frames, ort_int8, noisy):
    before = set(Path(tempfile.gettempdir()).glob("drake-cert-int8.*"))
    again = evaluated_model(model, backend="onnxruntime", quantization="int8",
                            calibration=Int8Calibration(calibration_frames, SIGMA))
    assert torch.equal(again(noisy), ort_int8(noisy))
    assert set(Path(tempfile.gettempdir()).glob("drake-cert-int8.*")) == before


def test_bad_combinations_are_refused(model):
    with pytest.raises(CertificationError, match="torch, onnxruntime"):
        evaluated_model(model, backend="tensorrt")
    with pytest.raises(CertificationError, match="none, int8"):
        evaluated_model(model, backend="onnxruntime", quantization="int4")
    with pytest.raises(CertificationError, match="bf16"):
        evaluated_model(model, backend="onnxruntime", precision="bf16")
    with pytest.raises(CertificationError, match="onnxruntime"):
        evaluated_model(model, backend="torch", quantization="int8")
    if onnxruntime_available():
        with pytest.raises(CertificationError, match="calibration_frames"):
            evaluated_model(model, backend="onnxruntime", quantization="int8",
                            calibration=Int8Calibration(None, SIGMA))
    assert resolve_backend("torch") == "torch" and resolve_backend("auto") in BACKENDS
    assert evaluated_model(model) is model


def test_without_onnxruntime_the_module_imports_and_says_how_to_install():
    code = """
import sys
sys.modules["onnxruntime"] = sys.modules["onnx"] = None  # as if not installed
from drake_cert.certification.backends import evaluated_model, resolve_backend
from drake_cert.errors import CertificationError
from drake_cert.perception.models import SmallResNet
assert resolve_backend("auto") == "torch"
try:
    evaluated_model(SmallResNet(3, width=8), backend="onnxruntime")
except CertificationError as e:
    print(e)
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert "pip install 'drake-cert[onnx]'" in out.stdout
