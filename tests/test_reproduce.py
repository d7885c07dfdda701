"""`drake-cert reproduce --quick`: the paper's tables from per-frame episodes, identical rows
whatever the executor, every row recomputable alone."""

import csv
import json
import time

import pytest

from drake_cert.cli import main
from drake_cert.experiments.reproduce import recompute_frame
from drake_cert.experiments.reproduce_config import (
    CALIBRATION,
    CELL,
    FRAME_CHOICE,
    ReproduceConfig,
    seed_of,
)
from drake_cert.experiments.tables import COLUMNS

QUICK_ARGS = ["reproduce", "--quick", "--no-plots"]


@pytest.fixture(scope="module")
def quick_local(tmp_path_factory):
    out = tmp_path_factory.mktemp("local")
    assert main([*QUICK_ARGS, "--out", str(out)]) == 0
    return out


def read_csv(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_quick_run_writes_every_table_with_the_required_columns(quick_local):
    rows = read_csv(quick_local / "results.csv")
    assert set(COLUMNS) <= set(rows[0])
    presets = {r["preset"] for r in rows}
    assert presets == {"carla-like", "rtk-like", "robotcar-like"}
    tables = {r["table"] for r in rows}
    assert {"f_clean", "f_sa", "f_ea", "g_clean", "g_sa", "g_ea", "f_reg_clean", "h_sa",
            "h_ea"} <= tables
    for r in rows:
        assert int(r["frames"]) == ReproduceConfig.quick().frames
        assert 0.0 <= float(r["instability_pct"]) <= 100.0
    md = (quick_local / "tables.md").read_text()
    assert "(98.60)" in md  # the paper's clean accuracy on Carla, beside ours


def test_the_certified_pipeline_never_leaves_the_lane_where_its_interval_covers(quick_local):
    for r in read_csv(quick_local / "frames.csv"):
        if r["pipeline"] == "g" and r["interval_covers"] == "True":
            assert r["left_lane"] == "False", r


def test_a_frame_recomputed_alone_gives_the_same_rows(quick_local):
    config = ReproduceConfig.quick()
    alone = recompute_frame(config, "rtk-like", 1)
    full = [r for r in read_csv(quick_local / "frames.csv")
            if r["preset"] == "rtk-like" and r["position"] == "1"]
    assert len(alone) == len(full)
    for a, f in zip(alone, full, strict=True):
        assert f"{a['velocity_mps']:.6g}" == f["velocity_mps"]
        assert f"{a['interval_lo']:.6g}" == f["interval_lo"]
        assert str(a["left_lane"]) == f["left_lane"]
        assert a["seed"] == f["seed"]


def test_ray_with_two_workers_gives_identical_results(quick_local, tmp_path):
    pytest.importorskip("ray")
    assert main([*QUICK_ARGS, "--out", str(tmp_path), "--executor", "ray",
                 "--workers", "2"]) == 0
    assert (tmp_path / "results.csv").read_text() == (quick_local / "results.csv").read_text()
    assert (tmp_path / "frames.csv").read_text() == (quick_local / "frames.csv").read_text()


def test_no_two_streams_share_a_seed():
    from systems import streams

    config = ReproduceConfig.quick()
    seeds = [seed_of(config, p, FRAME_CHOICE) for p in range(3)]
    seeds += [seed_of(config, p, CALIBRATION, s) for p in range(3) for s in range(3)]
    cells = [seed_of(config, p, CELL, c) for p in range(3) for c in range(len(config.cells()))]
    seeds += cells
    seeds += [streams.stream_seed(cell, purpose, frame) for cell in cells for frame in range(50)
              for purpose in (streams.ATTACK, streams.CERTIFICATE)]
    assert len(set(seeds)) == len(seeds)


def test_bad_reproduce_inputs_exit_2(tmp_path, capsys):
    assert main(["reproduce", "--quick", "--presets", "mars-like", "--out", str(tmp_path)]) == 2
    assert "mars-like" in capsys.readouterr().err
    blocker = tmp_path / "file"
    blocker.write_text("x")
    assert main(["reproduce", "--quick", "--out", str(blocker / "sub")]) == 2
    assert main(["reproduce", "--quick", "--frames", "0", "--out", str(tmp_path)]) == 2
    store = tmp_path / "kept" / "store"
    store.mkdir(parents=True)
    assert main(["reproduce", "--quick", "--from-store", "--fresh", "--out",
                 str(tmp_path / "kept")]) == 2
    assert store.exists()  # refused before anything was deleted
    assert main(["reproduce", "--quick", "--budget-min", "0", "--out", str(tmp_path)]) == 2


@pytest.mark.parametrize("address, message", [
    ("127.0.0.1:1", "no Ray cluster answers at 127.0.0.1:1"),  # nothing listens on port 1
    ("ray://127.0.0.1:1", "no Ray cluster answers at 127.0.0.1:1"),
    ("head-node", "expected 'auto', 'HOST:PORT' or 'ray://HOST:PORT'"),
])
def test_an_unreachable_cluster_address_is_refused_at_once(tmp_path, capsys, address, message):
    # Ray alone retries such an address for minutes without a word.
    start = time.perf_counter()
    assert main(["reproduce", "--quick", "--executor", "ray", "--address", address,
                 "--out", str(tmp_path)]) == 2
    assert message in capsys.readouterr().err
    assert time.perf_counter() - start < 10


def test_reproduce_runs_g_through_the_conformal_interval_when_asked():
    """12 calibration frames per label are too few for alpha_c = 0.008 (124 needed): every
    label is then in the conformal set, so every g interval is the envelope -- which the
    safe-set interval of a confidently classified frame never is."""
    import dataclasses

    from drake_cert.config import load_conditions

    config = dataclasses.replace(ReproduceConfig.quick(), presets=("carla-like",),
                                 interval="conformal", conformal_per_class=12, conformal_n=100,
                                 regression=False)
    envelope = load_conditions().envelope("carla-like")
    rows = [r for r in recompute_frame(config, "carla-like", 0) if r["pipeline"] == "g"]
    assert rows
    for r in rows:
        assert (r["interval_lo"], r["interval_hi"]) == tuple(envelope), r
        assert r["interval_lo"] <= r["stiffness_n_per_rad"] <= r["interval_hi"]
    safe_set = recompute_frame(dataclasses.replace(config, interval="safe_set"), "carla-like", 0)
    assert any((r["interval_lo"], r["interval_hi"]) != tuple(envelope)
               for r in safe_set if r["pipeline"] == "g")


class CountingExecutor:
    """The in-process executor, counting the tasks it runs."""

    def __init__(self):
        from drake_cert.experiments.executors import LocalExecutor

        self.inner, self.ran = LocalExecutor(), 0

    def map(self, make_worker, tasks, progress=None, on_result=None, stop=None):
        def counted(index, result):
            self.ran += 1
            if on_result is not None:
                on_result(index, result)

        return self.inner.map(make_worker, tasks, progress, on_result=counted, stop=stop)


def test_a_stopped_run_resumes_from_its_store_with_the_same_rows(quick_local, tmp_path):
    """Stop after the first frame, rerun: only the second frame (and no calibration) is
    computed, and the rows equal those of the uninterrupted run."""
    import dataclasses

    from drake_cert.experiments.reproduce import run_reproduction
    from drake_cert.experiments.run_store import RunStore

    config = dataclasses.replace(ReproduceConfig.quick(), presets=("rtk-like",))
    store = RunStore(tmp_path / "store")
    first = CountingExecutor()
    rows = run_reproduction(config, first, store=store, stop=lambda: first.ran >= 4)
    assert {r["position"] for r in rows} == {0}  # 3 betas + 1 frame, then stopped
    again = CountingExecutor()
    rows = run_reproduction(config, again, store=store)
    assert again.ran == 1
    full = [r for r in read_csv(quick_local / "frames.csv") if r["preset"] == "rtk-like"]
    assert len(rows) == len(full)
    for a, f in zip(rows, full, strict=True):
        assert (a["position"], a["pipeline"], a["attack"]) == (int(f["position"]),
                                                              f["pipeline"], f["attack"])
        assert f"{a['velocity_mps']:.6g}" == f["velocity_mps"]
        assert f"{a['interval_hi']:.6g}" == f["interval_hi"]
    # A store made with other settings is not reused: nothing stored matches n = 300.
    other = dataclasses.replace(config, n=300)
    assert run_reproduction(other, CountingExecutor(), store=store, stop=lambda: True) == []


def test_from_store_rewrites_the_same_tables_and_the_claims_without_computing(quick_local,
                                                                               tmp_path, capsys):
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(quick_local, copy)
    (copy / "results.csv").unlink()
    assert main([*QUICK_ARGS, "--out", str(copy), "--from-store"]) == 0
    assert (copy / "results.csv").read_text() == (quick_local / "results.csv").read_text()
    assert "g inside its certificates" in (copy / "claims.md").read_text()
    # The printed summary carries the claims' verdicts, as claims.json states them.
    printed = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    claims = json.loads((copy / "claims.json").read_text())
    assert printed["claims_hold"] == {p: c["holds"] for p, c in claims.items()}
    assert set(printed["claims_hold"]) == {"carla-like", "rtk-like", "robotcar-like"}
    assert main([*QUICK_ARGS, "--out", str(tmp_path / "empty"), "--from-store"]) == 2
    assert "holds no frame" in capsys.readouterr().err


def test_conformal_calibrations_run_on_the_executor_and_resume_from_the_store(tmp_path):
    """g's conformal calibrations are executor tasks kept in the store: a rerun computes only
    the frame left, and every row equals the frame computed alone (which calibrates itself)."""
    import dataclasses

    from drake_cert.experiments.calibrations import conformal_sigmas
    from drake_cert.experiments.reproduce import run_reproduction
    from drake_cert.experiments.run_store import RunStore

    config = dataclasses.replace(ReproduceConfig.quick(), presets=("rtk-like",),
                                 interval="conformal", conformal_per_class=12, conformal_n=100,
                                 regression=False)
    calibrations = len(conformal_sigmas(config))
    store = RunStore(tmp_path / "store")
    first = CountingExecutor()
    run_reproduction(config, first, store=store, stop=lambda: first.ran >= calibrations + 1)
    assert (tmp_path / "store" / "conformal.json").exists()
    again = CountingExecutor()
    rows = run_reproduction(config, again, store=store)
    assert again.ran == 1  # the second frame; no calibration
    alone = recompute_frame(config, "rtk-like", 1)
    assert [r for r in rows if r["position"] == 1] == alone
