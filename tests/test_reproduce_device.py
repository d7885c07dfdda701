"""Where a reproduction samples its models: --device cpu with torch gives the rows the run gave
before the device existed; ONNX Runtime agrees with them to float rounding; CUDA is refused in
one line where it is absent."""

import dataclasses
import json
import math
from pathlib import Path

import pytest
import torch

from drake_cert.cli import main
from drake_cert.errors import ConfigError
from drake_cert.experiments.reproduce import FrameWorker
from drake_cert.experiments.reproduce_config import FrameTask, ReproduceConfig
from drake_cert.experiments.run_store import identity_parts

# Rows of ReproduceConfig.quick() in fp32 (carla-like frame 0, rtk-like frame 1), computed by
# the code before --device and --backend existed (git 1e73b73, torch on the CPU).
BEFORE = Path(__file__).parent / "data" / "reproduce_quick_rows_cpu_torch.json"
DECISION = ("predicted", "certified", "design_labels", "left_lane", "velocity_mps")
FLOATS = ("interval_lo", "interval_hi", "certificate")


def _config(**changes) -> ReproduceConfig:
    # one preset, classification only: the cells it has draw the noise they draw in the full
    # quick run (cell seeds are keyed by what the cell is)
    settings = dict(precision="fp32", presets=("carla-like",), sigmas=(0.25,), regression=False,
                    conformal=False, decisions="fixed")
    return dataclasses.replace(ReproduceConfig.quick(), **{**settings, **changes})


@pytest.fixture(scope="module")
def designs(default_design_table):
    """The shipped design table (the session's, synthesized once per test process)."""
    return default_design_table.designs


def _frame(config, designs) -> list[dict]:
    """carla-like frame 0 computed alone on one thread (as reproduce.recompute_frame)."""
    from drake_cert.threads import torch_threads

    with torch_threads(1):
        return FrameWorker(config, designs=designs)(FrameTask("carla-like", 0))


def _before() -> dict:
    rows = json.loads(BEFORE.read_text())
    return {(r["pipeline"], r["sigma"], r["attack"], r["eps"]): r for r in rows
            if r["preset"] == "carla-like" and r["position"] == 0}


def _close(a, b) -> bool:
    if isinstance(a, str) or isinstance(b, str):
        return a == b
    return a == b or math.isclose(float(a), float(b), rel_tol=1e-4, abs_tol=1e-6)


def test_cpu_with_torch_gives_the_rows_of_the_run_before_the_device_existed(designs):
    before = _before()
    rows = _frame(_config(device="cpu", backend="torch"), designs)
    assert len(rows) == 6  # f and g (sigma 0.25), clean, SA and EA
    for r in rows:
        old = before[(r["pipeline"], r["sigma"], r["attack"], r["eps"])]
        assert all(r[k] == old[k] for k in DECISION), (r, old)
        assert all(_close(r[k], old[k]) for k in FLOATS), (r, old)


def test_onnx_runtime_takes_the_same_decisions_as_torch(designs):
    pytest.importorskip("onnxruntime", reason="ONNX Runtime is the optional 'onnx' extra; "
                        "without it the reproduction evaluates in torch, tested above")
    before = _before()
    config = _config(backend="onnxruntime")
    assert config.backend == "onnxruntime"
    for r in _frame(config, designs):
        old = before[(r["pipeline"], r["sigma"], r["attack"], r["eps"])]
        assert all(_close(r[k], old[k]) for k in (*DECISION, *FLOATS)), (r, old)


def test_the_device_and_backend_are_resolved_and_part_of_the_run_identity():
    torch_cpu = _config(backend="torch")
    assert (torch_cpu.device, torch_cpu.backend) == ("cpu", "torch")
    settings = identity_parts(torch_cpu, [])["settings"]
    assert (settings["device"], settings["backend"]) == ("cpu", "torch")
    assert _config(backend="auto").backend in ("torch", "onnxruntime")  # never "auto"
    with pytest.raises(ConfigError, match="not cpu or cuda"):
        _config(device="tpu")
    # bf16 runs in torch (ONNX Runtime is fp32 only); the command line refuses the pair
    assert dataclasses.replace(_config(backend="onnxruntime"), precision="bf16").backend == \
        "torch"


def test_onnx_runtime_in_bf16_is_refused_in_one_line(tmp_path, capsys):
    code = main(["reproduce", "--quick", "--backend", "onnxruntime", "--precision", "bf16",
                 "--out", str(tmp_path / "r")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "evaluates in fp32" in err[0]


@pytest.mark.skipif(torch.cuda.is_available(),
                    reason="CUDA is present here, so --device cuda is not refused: the refusal "
                           "is what this test checks, on the machines (CI) that lack CUDA")
def test_cuda_is_refused_in_one_line_where_it_is_absent(tmp_path, capsys):
    code = main(["reproduce", "--quick", "--device", "cuda", "--out", str(tmp_path / "r")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1
    assert "CUDA is not available here" in err[0] and "--device cpu" in err[0]
    assert not (tmp_path / "r").exists()  # refused before anything is written


def test_at_the_papers_budget_every_pipeline_runs_and_a_budget_beyond_reach_draws_nothing(
        designs):
    """eps = 1 (the paper's delta = 255) has g and h at every sigma and f_reg; where sigma is
    so small that n samples could never certify eps, the cell is the envelope without any
    attack or sample (what sampling would have given)."""
    from drake_cert.experiments.reproduce_config import PAPER_BUDGET_EPS, max_certifiable_radius

    default = ReproduceConfig(precision="fp32")
    at_paper = {(p, s) for p, s, _, e in default.cells() if e == PAPER_BUDGET_EPS}
    assert {("g", s) for s in default.sigmas} | {("h", s) for s in default.sigmas} | \
        {("f_reg", 0.0), ("f", 0.0)} <= at_paper
    config = dataclasses.replace(ReproduceConfig.quick(), precision="fp32",
                                 presets=("carla-like",), sigmas=(0.25,), conformal=False,
                                 sweep_eps=(0.25, PAPER_BUDGET_EPS))
    assert max_certifiable_radius(0.25, config.n, config.alpha) < PAPER_BUDGET_EPS
    worker = FrameWorker(config, designs=designs, betas={("carla-like", 0.25): 5000.0})
    assert worker.decision_rule("carla-like", ("g", 0.25, "sa", 1.0)) == "never"
    assert worker.decision_rule("carla-like", ("h", 0.25, "sa", 1.0)) == "never"
    assert worker.decision_rule("carla-like", ("g", 0.25, "sa", 0.25)) == "fixed"  # a radius
    assert worker.decision_rule("carla-like", ("g", 0.25, "none", 0.25)) == "sequential"
    from drake_cert.threads import torch_threads

    with torch_threads(1):
        rows = worker(FrameTask("carla-like", 0))
    never = [r for r in rows if r["eps"] == 1.0 and r["pipeline"] in ("g", "h")]
    assert len(never) == 4 and not any(r["certified"] for r in never)
    for r in never:
        interval = (r["interval_lo"], r["interval_hi"])
        assert interval == tuple(worker.conditions.envelope("carla-like")), r
    assert {r["pipeline"] for r in rows if r["eps"] == 1.0} == {"f", "g", "f_reg", "h"}


def test_h_decides_its_median_over_the_designs_candidate_intervals(designs):
    """Each candidate sits beta (and one N/rad) inside a design's ends, open where the design
    reaches the envelope; a certified decision drives the design whose interval it came from,
    and an infinite beta leaves no candidate (h keeps its fixed-n bounds, the envelope)."""
    import math

    from drake_cert.certification.intervals import INSIDE_N_PER_RAD, median_candidates
    from drake_cert.config import load_conditions
    from drake_cert.synthesis.selection import preset_designs
    from drake_cert.threads import torch_threads

    conditions = load_conditions()
    mine = preset_designs(designs, conditions, "carla-like")
    env = conditions.envelope("carla-like")
    cands = median_candidates(mine, 8000.0, env)
    assert cands and median_candidates(mine, math.inf, env) == []
    for lo, hi in cands:
        holder = [d for d in mine if (lo == -math.inf and d.stiffness_lo_n_per_rad == env[0]
                                      or d.stiffness_lo_n_per_rad + 8000.0 + INSIDE_N_PER_RAD
                                      == lo)
                  and (hi == math.inf and d.stiffness_hi_n_per_rad == env[1]
                       or d.stiffness_hi_n_per_rad - 8000.0 - INSIDE_N_PER_RAD == hi)]
        assert holder, (lo, hi)
    config = dataclasses.replace(_config(decisions="sequential"), regression=True, n=2000)
    worker = FrameWorker(config, designs=designs, betas={("carla-like", 0.25): 8000.0})
    assert worker.decision_rule("carla-like", ("h", 0.25, "sa", 0.25)) == "sequential"
    with torch_threads(1):
        rows = [r for r in worker(FrameTask("carla-like", 0)) if r["pipeline"] == "h"]
    assert rows and all(r["certified"] for r in rows)
    for r in rows:  # the certified design, narrower than the envelope, holds the interval
        lo, hi = conditions.hull(r["design_labels"].split("+"))
        assert (lo, hi) != env and lo <= r["interval_lo"] and r["interval_hi"] <= hi
        assert r["interval_lo"] <= r["stiffness_n_per_rad"] <= r["interval_hi"]
