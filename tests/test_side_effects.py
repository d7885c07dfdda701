"""What the library does to the process and the disk without being asked: the data cache of a
source checkout, and glibc's allocator left alone by the sampler (only long-running commands
change it, explicitly)."""

from pathlib import Path

import pytest
import torch

from drake_cert.certification import sampler
from drake_cert.certification.classifier import SmoothedClassifier
from drake_cert.perception import datasets

ROOT = Path(__file__).resolve().parents[1]


def test_the_data_cache_is_on_in_a_source_checkout_by_default(monkeypatch):
    monkeypatch.delenv("DRAKE_CERT_DATA_CACHE", raising=False)
    assert (ROOT / "pyproject.toml").is_file()  # this test runs from a source checkout
    assert datasets.disk_cache_dir() == ROOT / "data_cache"
    monkeypatch.setenv("DRAKE_CERT_DATA_CACHE", "")
    assert datasets.disk_cache_dir() is None


def test_building_and_running_a_sampler_leaves_the_allocator_alone(monkeypatch):
    def refuse():
        pytest.fail("retain_freed_memory called by the library, not by an entry point")

    monkeypatch.setattr(sampler, "retain_freed_memory", refuse)
    torch.manual_seed(0)
    model = torch.nn.Sequential(torch.nn.Flatten(), torch.nn.Linear(3 * 8 * 8, 2)).eval()
    counts = SmoothedClassifier(model, 2, 0.5).sample_counts(
        torch.full((3, 8, 8), 0.5), 50, 25, torch.Generator().manual_seed(0))
    assert int(counts.sum()) == 50


def test_certify_keeps_freed_memory_and_synthesize_does_not(monkeypatch, tmp_path, capsys):
    from drake_cert import cli

    calls = []
    monkeypatch.setattr(sampler, "retain_freed_memory", lambda: calls.append(True))
    assert cli.main(["synthesize", "--vehicle", str(tmp_path / "missing.yaml")]) == 2
    assert calls == []
    # no model in an empty folder: certify fails after the allocator setting, before sampling
    assert cli.main(["certify", "--preset", "rtk-like", "--sigma", "0.25", "--models",
                     str(tmp_path)]) == 2
    assert calls == [True]
    assert {"certify", "drive", "calibrate", "reproduce"} == set(cli.LONG_SAMPLING)
    capsys.readouterr()
