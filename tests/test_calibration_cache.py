"""The calibration cache returns what the computation returns, and computes anew for any other
input, code or an unreadable entry (drake_cert.certification.calibration_cache)."""

import json

from drake_cert.certification import calibration_cache as cc


def test_a_cached_calibration_is_the_computed_one_and_any_other_key_computes_anew(
        tmp_path, monkeypatch):
    monkeypatch.setenv(cc.CACHE_ENV, str(tmp_path))
    calls = []

    def compute(value):
        def run():
            calls.append(value)
            return {"thresholds": {"0": value}}
        return run

    key = {"model_sha256": "ab", "n": 1000, "root_seed": 7}
    assert cc.cached("robust_conformal", key, compute(0.25)) == {"thresholds": {"0": 0.25}}
    assert cc.cached("robust_conformal", key, compute(0.5)) == {"thresholds": {"0": 0.25}}
    assert calls == [0.25]  # the second call read the entry
    assert cc.cached("robust_conformal", {**key, "n": 500}, compute(0.5))["thresholds"] == \
        {"0": 0.5}
    (entry,) = [p for p in tmp_path.iterdir()
                if json.loads(p.read_text())["key"]["n"] == 1000]
    stored = json.loads(entry.read_text())
    assert stored["key"]["code"] == cc.code_digest()  # the code that computed it is in the key
    entry.write_text("{not json")  # a torn or foreign entry is computed anew, not trusted
    assert cc.cached("robust_conformal", key, compute(0.75))["thresholds"] == {"0": 0.75}
    monkeypatch.setenv(cc.CACHE_ENV, "off")
    cc.cached("robust_conformal", key, compute(1.0))
    assert calls == [0.25, 0.5, 0.75, 1.0]
