"""bfloat16 evaluation: the certificate is that of the bfloat16 model as evaluated."""

import numpy as np
import pytest
import torch

from drake_cert.certification.classifier import SmoothedClassifier
from drake_cert.certification.sampler import Bfloat16Model, with_precision
from drake_cert.errors import CertificationError
from drake_cert.perception.models import SmallResNet


@pytest.fixture(scope="module")
def model():
    torch.manual_seed(0)
    return SmallResNet(3, width=8).eval()


def test_bf16_certificate_counts_are_those_of_the_bf16_model(model):
    x = torch.rand(3, 16, 16, generator=torch.Generator().manual_seed(1))
    smooth = SmoothedClassifier(model, 3, 0.25, precision="bf16")
    counts = smooth.sample_counts(x, 300, 100, torch.Generator().manual_seed(5))
    # The same noise, drawn and added in float32, through the bf16 model by hand:
    g = torch.Generator().manual_seed(5)
    bf16 = Bfloat16Model(model).eval()
    expected = np.zeros(3, dtype=np.int64)
    with torch.inference_mode():
        for _ in range(3):
            z = torch.empty(100, 3, 16, 16).normal_(0.0, 0.25, generator=g) + x
            expected += np.bincount(bf16(z).argmax(1).numpy(), minlength=3)
    assert (counts == expected).all()


def test_bf16_model_agrees_with_float32_on_most_noisy_frames(model):
    z = torch.rand(200, 3, 16, 16, generator=torch.Generator().manual_seed(2))
    with torch.inference_mode():
        a, b = model(z), with_precision(model, "bf16")(z)
    assert b.dtype == torch.float32
    assert (a.argmax(1) == b.argmax(1)).float().mean() > 0.9
    assert with_precision(model, "fp32") is model


def test_unknown_precision_is_rejected(model):
    with pytest.raises(CertificationError, match="precision"):
        SmoothedClassifier(model, 3, 0.25, precision="fp8")


def test_auto_is_fp32_where_the_probe_finds_no_native_bf16(monkeypatch):
    from drake_cert.certification import backends, sampler

    monkeypatch.delenv(sampler.PRECISION_ENV, raising=False)
    monkeypatch.setattr(backends, "onnxruntime_available", lambda: False)
    monkeypatch.setattr(sampler, "bf16_supported", lambda: False)
    assert sampler.resolve_precision("auto") == "fp32"
    monkeypatch.setattr(sampler, "bf16_supported", lambda: True)
    assert sampler.resolve_precision("auto") == "bf16"  # torch only: bf16 beats torch fp32
    assert sampler.resolve_precision("fp32") == "fp32"  # explicit choices mean themselves


def test_auto_is_onnx_runtime_fp32_wherever_it_is_installed_even_with_native_bf16(
        monkeypatch):
    # measured on two CPUs with native bf16 (DESIGN 3.8): ONNX Runtime fp32 was the faster
    from drake_cert.certification import backends, sampler

    monkeypatch.delenv(sampler.PRECISION_ENV, raising=False)
    monkeypatch.setattr(backends, "onnxruntime_available", lambda: True)
    monkeypatch.setattr(sampler, "bf16_supported", lambda: True)
    assert sampler.resolve_precision("auto") == "fp32"
    assert backends.resolve_backend("auto", sampler.resolve_precision("auto")) == "onnxruntime"


def test_the_environment_fixes_what_auto_means_for_the_process(monkeypatch):
    from drake_cert.certification import sampler

    monkeypatch.setattr(sampler, "bf16_supported", lambda: True)
    monkeypatch.setenv(sampler.PRECISION_ENV, "fp32")
    assert sampler.resolve_precision("auto") == "fp32"
    monkeypatch.setenv(sampler.PRECISION_ENV, "fp16")
    with pytest.raises(CertificationError, match="DRAKE_CERT_PRECISION"):
        sampler.resolve_precision("auto")


def test_a_drive_and_a_certify_run_report_the_precision_they_used(monkeypatch, tmp_path,
                                                                  capsys):
    import json

    from drake_cert.certification import sampler
    from drake_cert.cli import main

    monkeypatch.delenv(sampler.PRECISION_ENV, raising=False)
    monkeypatch.setattr(sampler, "bf16_supported", lambda: False)  # only the probe is mocked
    assert main(["drive", "--scenario", "dry_to_snow", "--duration", "0.4", "--json",
                 "--n", "100", "--out", str(tmp_path / "tape.csv")]) == 0  # n: test budget
    summary = json.loads(capsys.readouterr().out)
    assert summary["precision"] == "fp32" and summary["decision"] == "sequential"
    stored = [line for line in (tmp_path / "tape.csv").read_text().splitlines()
              if line.startswith("# summary ")]
    assert json.loads(stored[0][len("# summary "):])["precision"] == "fp32"
    assert main(["certify", "--preset", "carla-like", "--sigma", "0.25", "--frames", "3",
                 "--n", "100", "--n0", "10", "--attack-steps", "2", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["summary"]["precision"] == "fp32"
