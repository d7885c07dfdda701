"""`drake-cert reproduce --quick`: the paper's tables from per-frame episodes, identical rows
whatever the executor, every row recomputable alone."""

import csv
import json
import time
from pathlib import Path

import pytest

from drake_cert.cli import main
from drake_cert.experiments.claims import preset_claims
from drake_cert.experiments.paper_claims import failing
from drake_cert.experiments.reproduce import recompute_frame
from drake_cert.experiments.reproduce_config import ReproduceConfig, cell_seed
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
    # meta.json records the workers' CPU time per stage beside the wall time
    meta = json.loads((quick_local / "meta.json").read_text())
    cpu = meta["total_cpu_s"]
    assert cpu["frames"] > 0 and cpu["calibration_h"] > 0 and cpu["calibration_conformal"] > 0
    assert cpu["all"] == pytest.approx(cpu["frames"] + cpu["calibration_h"]
                                       + cpu["calibration_conformal"], abs=0.11)
    assert cpu["invocations_without"] == 0 and meta["runs"][-1]["cpu_s"]["frames"] > 0
    # ... and the machine: the CPU's model name and the cores the run had
    assert meta["machine"]["cpu"] and meta["machine"]["cores"] >= 1
    assert meta["machine"] == meta["runs"][-1]["machine"]
    assert meta["config"]["conformal_alpha_c"] == 0.5  # the quick run's; the drive's by default
    # one invocation: the store's ledger holds the same seconds, and a part count per stage
    ledger = meta["store_cpu_s"]
    assert ledger["frames_parts"] == 6 and ledger["all"] == pytest.approx(cpu["all"], abs=0.2)
    rows = read_csv(quick_local / "results.csv")
    assert set(COLUMNS) <= set(rows[0])
    presets = {r["preset"] for r in rows}
    assert presets == {"carla-like", "rtk-like", "robotcar-like"}
    tables = {r["table"] for r in rows}
    assert {"f_clean", "f_sa", "f_ea", "g_clean", "g_sa", "g_ea", "g_conformal_clean",
            "g_conformal_sa", "g_conformal_ea", "f_reg_clean", "h_sa", "h_ea"} <= tables
    for r in rows:
        assert int(r["frames"]) == ReproduceConfig.quick().frames
        assert 0.0 <= float(r["instability_pct"]) <= 100.0
    md = (quick_local / "tables.md").read_text()
    assert "(98.60)" in md  # the paper's clean accuracy on Carla, beside ours


def test_the_certified_pipeline_never_leaves_the_lane_where_its_interval_covers(quick_local):
    for r in read_csv(quick_local / "frames.csv"):
        if r["pipeline"] in ("g", "g_conformal") and r["interval_covers"] == "True":
            assert r["left_lane"] == "False", r


@pytest.mark.slow  # ~25 s on 2 cores
def test_a_frame_recomputed_alone_in_a_smaller_run_gives_the_same_rows(quick_local):
    """One preset, no regression, no g_conformal: each cell draws the noise it draws in the full
    run (cell seeds are keyed by what the cell is, not by its place in the run's list)."""
    import dataclasses

    config = dataclasses.replace(ReproduceConfig.quick(), presets=("rtk-like",),
                                 regression=False, conformal=False)
    alone = recompute_frame(config, "rtk-like", 1)
    full = {(r["pipeline"], r["sigma"], r["attack"], r["eps"]): r
            for r in read_csv(quick_local / "frames.csv")
            if r["preset"] == "rtk-like" and r["position"] == "1"}
    assert {a["pipeline"] for a in alone} == {"f", "g"}
    for a in alone:
        f = full[(a["pipeline"], f"{a['sigma']:.6g}", a["attack"], f"{a['eps']:.6g}")]
        assert str(a["predicted"]) == f["predicted"]
        assert f"{a['certificate']:.6g}" == f["certificate"]
        assert f"{a['velocity_mps']:.6g}" == f["velocity_mps"]
        assert f"{a['interval_lo']:.6g}" == f["interval_lo"]
        assert str(a["left_lane"]) == f["left_lane"]
        assert a["seed"] == f["seed"]


# A real loopback cluster checks the same byte identity in the main suite
# (tests/test_ray_cluster.py); the local Ray with two workers runs with the slow tests.
@pytest.mark.slow
def test_ray_with_two_workers_gives_identical_results(quick_local, tmp_path):
    pytest.importorskip("ray")
    assert main([*QUICK_ARGS, "--out", str(tmp_path), "--executor", "ray",
                 "--workers", "2"]) == 0
    assert (tmp_path / "results.csv").read_text() == (quick_local / "results.csv").read_text()
    assert (tmp_path / "frames.csv").read_text() == (quick_local / "frames.csv").read_text()


def test_no_two_streams_share_a_seed_and_both_g_pipelines_share_their_noise():
    from drake_cert.certification.seeds import Purpose, child_seed
    from drake_cert.experiments.reproduce_config import calibration_seed, noise_cell

    config = ReproduceConfig()
    presets = config.presets
    cells = config.cells()
    owners = {p: {noise_cell(c) for c in cells} for p in presets}
    roots = [cell_seed(config, p, c) for p in presets for c in sorted(owners[p])]
    seeds = roots + [child_seed(root, purpose, frame) for root in roots for frame in range(5)
                     for purpose in (Purpose.ATTACK, Purpose.SELECTION, Purpose.ESTIMATION)]
    seeds += [calibration_seed(config, purpose, p, s) for p in presets for s in config.sigmas
              for purpose in (Purpose.REGRESSION_CALIBRATION,)]
    assert len(set(seeds)) == len(seeds)
    for p in presets:
        for pipeline, sigma, attack, eps in cells:
            if pipeline == "g_conformal":  # one attack and one certificate, two intervals
                assert cell_seed(config, p, (pipeline, sigma, attack, eps)) == \
                    cell_seed(config, p, ("g", sigma, attack, eps))


def test_bad_reproduce_inputs_exit_2(tmp_path, capsys):
    assert main(["reproduce", "--quick", "--presets", "mars-like", "--out", str(tmp_path)]) == 2
    assert "mars-like" in capsys.readouterr().err
    blocker = tmp_path / "file"
    blocker.write_text("x")
    assert main(["reproduce", "--quick", "--out", str(blocker / "sub")]) == 2
    assert main(["reproduce", "--quick", "--frames", "0", "--out", str(tmp_path)]) == 2
    capsys.readouterr()
    # too few g_conformal calibration frames for any threshold: refused before any is drawn
    assert main(["reproduce", "--quick", "--conformal-per-class", "3", "--out",
                 str(tmp_path)]) == 2
    assert "conformal_per_class = 3" in capsys.readouterr().err
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


def test_both_intervals_read_the_same_certificates_in_one_run(quick_local):
    """g_conformal reads g's certificate of the same attacked frame where the cell keeps a
    fixed-n certificate (same predicted label on every frame and attacked cell; the clean
    cells are decided sequentially, each interval on its own samples from the same streams).
    Each interval is the stiffness hull of a contiguous label range of the preset."""
    from drake_cert.config import load_conditions

    conditions = load_conditions()
    rows = read_csv(quick_local / "frames.csv")
    g = {(r["preset"], r["position"], r["sigma"], r["attack"], r["eps"]): r
         for r in rows if r["pipeline"] == "g"}
    conformal = [r for r in rows if r["pipeline"] == "g_conformal"]
    assert len(conformal) == len(g)
    for r in conformal:
        twin = g[(r["preset"], r["position"], r["sigma"], r["attack"], r["eps"])]
        assert r["seed"] == twin["seed"]
        if r["attack"] != "none":  # fixed n: the one certificate both intervals read
            assert r["predicted"] == twin["predicted"]
        hulls = {conditions.hull(labels) for labels in conditions.contiguous_ranges(r["preset"])}
        assert (float(r["interval_lo"]), float(r["interval_hi"])) in hulls, r


def test_the_interval_option_is_gone_with_a_pointer_to_the_new_pipeline(tmp_path, capsys):
    assert main(["reproduce", "--quick", "--interval", "conformal", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "g_conformal" in err and len(err.strip().splitlines()) == 1


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


@pytest.mark.slow  # ~70 s on 2 cores
def test_a_stopped_run_resumes_from_its_store_with_the_same_rows(quick_local, tmp_path):
    """Stop after the first frame, rerun: only the second frame (and no calibration) is
    computed, and the rows equal those of the uninterrupted run."""
    import dataclasses

    from drake_cert.experiments.calibrations import conformal_sigmas
    from drake_cert.experiments.reproduce import run_reproduction
    from drake_cert.experiments.run_store import RunStore

    config = dataclasses.replace(ReproduceConfig.quick(), presets=("rtk-like",))
    calibrations = len(config.sigmas) + len(conformal_sigmas(config))
    store = RunStore(tmp_path / "store")
    first = CountingExecutor()
    rows = run_reproduction(config, first, store=store,
                            stop=lambda: first.ran >= calibrations + 1)
    assert {r["position"] for r in rows} == {0}  # the calibrations + 1 frame, then stopped
    again = CountingExecutor()
    rows = run_reproduction(config, again, store=store)
    assert again.ran == 1
    # the store's CPU ledger counts every part once, whichever invocation made it
    (cost,) = json.loads((tmp_path / "store" / "cpu.json").read_text()).values()
    assert (cost["frames_parts"], cost["calibration_h_parts"],
            cost["calibration_conformal_parts"]) == (2, len(config.sigmas),
                                                     len(conformal_sigmas(config)))
    assert min(cost["frames"], cost["calibration_h"], cost["calibration_conformal"]) > 0
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


def test_from_store_rewrites_the_same_tables_and_the_claims_without_computing(
        quick_local, tmp_path, capsys, monkeypatch):
    """On a machine whose "auto" means the other precision (as a CPU without native bf16
    does for a bf16 store), --from-store reads the frames in the precision they were made in."""
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(quick_local, copy)
    (copy / "results.csv").unlink()
    made_in = json.loads((quick_local / "meta.json").read_text())["config"]["precision"]
    monkeypatch.setenv("DRAKE_CERT_PRECISION", "bf16" if made_in == "fp32" else "fp32")
    assert main([*QUICK_ARGS, "--out", str(copy), "--from-store"]) == 0
    assert json.loads((copy / "meta.json").read_text())["config"]["precision"] == made_in
    assert (copy / "frames.csv").read_text() == (quick_local / "frames.csv").read_text()
    assert (copy / "results.csv").read_text() == (quick_local / "results.csv").read_text()
    assert "g inside its certificates" in (copy / "claims.md").read_text()
    # The printed summary carries the claims' verdicts, as claims.json states them.
    printed = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    claims = json.loads((copy / "claims.json").read_text())
    assert list(claims)[:3] == ["headline", "truth_conditioned_diagnostic", "paper_claims"]
    assert printed["claims_hold"] == {p: c["holds"] for p, c in preset_claims(claims).items()}
    # ... and the paper's claims: how many have each verdict, those that do not hold by name
    assert printed["paper_claims"] == claims["paper_claims"]["counts"]
    assert sum(printed["paper_claims"].values()) == len(claims["paper_claims"]["claims"])
    assert printed["paper_claims_failing"] == failing(claims["paper_claims"])
    assert set(printed["claims_hold"]) == {"carla-like", "rtk-like", "robotcar-like"}
    assert main([*QUICK_ARGS, "--out", str(tmp_path / "empty"), "--from-store"]) == 2
    assert "holds no frame" in capsys.readouterr().err


def test_the_tables_name_the_revision_the_run_started_from_not_one_its_writes_dirtied(
        quick_local, tmp_path, monkeypatch):
    """Writing results into a tracked folder (results/paper) changes tracked files (its run log,
    its tables) before meta.json is written: the revision read then would be "-dirty" although
    the run started on a clean checkout. meta.json names the revision of the start."""
    import shutil

    import drake_cert.io as io_module

    copy = tmp_path / "copy"
    shutil.copytree(quick_local, copy)
    committed = (copy / "store" / "runs.json").read_text()
    reads = []

    def revision_dirtied_by_the_run_log():  # as git reads it: dirty once a tracked file changed
        reads.append((copy / "store" / "runs.json").read_text() != committed)
        return "abc1234-dirty" if reads[-1] else "abc1234"

    monkeypatch.setattr(io_module, "git_revision", revision_dirtied_by_the_run_log)
    assert main([*QUICK_ARGS, "--out", str(copy), "--from-store"]) == 0
    assert reads[0] is False and reads[-1] is True  # read again after the run log changed
    meta = json.loads((copy / "meta.json").read_text())
    assert meta["written_by_revision"] == "abc1234"
    assert json.loads((copy / "store" / "runs.json").read_text())[-1]["git_revision"] == \
        "abc1234"


@pytest.mark.slow  # ~60 s on 2 cores
def test_conformal_calibrations_run_on_the_executor_and_resume_from_the_store(tmp_path):
    """g's conformal calibrations are executor tasks kept in the store: a rerun computes only
    the frame left, and every row equals the frame computed alone (which calibrates itself)."""
    import dataclasses

    from drake_cert.experiments.calibrations import conformal_sigmas
    from drake_cert.experiments.reproduce import run_reproduction
    from drake_cert.experiments.run_store import RunStore

    config = dataclasses.replace(ReproduceConfig.quick(), presets=("rtk-like",),
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


def _nudged(designs, factor: float = 1.0 + 6e-5, field=None, labels=None):
    """The design table with every float multiplied by ``factor`` (or only ``field`` of the
    design of ``labels``), as another CPU's last digits would move it."""
    import dataclasses

    from drake_cert.synthesis.design import ControllerDesign

    def walk(x):
        if isinstance(x, float):
            return x * factor
        if isinstance(x, dict):
            return {k: walk(v) for k, v in x.items()}
        if isinstance(x, list):
            return [walk(v) for v in x]
        return x

    out = []
    for d in designs:
        fields = dataclasses.asdict(d)
        if field is None:
            fields = walk(fields)
        elif d.labels == labels:
            fields[field] = fields[field] * factor
        out.append(ControllerDesign(**fields))
    return out


def test_the_run_identity_ignores_machine_digits_but_not_a_real_change(default_design_table,
                                                                       tmp_path):
    """A store keeps the design table it was made with; a table whose every float moved by
    6e-5 relative (as another CPU's solve moves it) is that table, one with a safe speed changed
    in its 4th digit is not."""
    from drake_cert.experiments.run_store import RunStore, design_dicts, run_identity

    config = ReproduceConfig.quick()
    designs = default_design_table.designs
    store = RunStore(tmp_path / "store")
    identity = store.identity(config, designs)
    store.put_betas(identity, {})  # the first write records the identity's design table
    assert identity == run_identity(config, designs)
    nudged = _nudged(designs)
    assert any(a.k_m != b.k_m for a, b in zip(nudged, designs, strict=True))
    assert RunStore(tmp_path / "store").identity(config, nudged) == identity
    assert run_identity(config, nudged, references=[design_dicts(designs)]) == identity
    sunny = next(d for d in designs if d.labels == ["sunny"])
    faster = _nudged(designs, factor=(sunny.speed_mps + 0.01) / sunny.speed_mps,
                     field="speed_mps", labels=["sunny"])  # 19.36 -> 19.37 m/s
    assert RunStore(tmp_path / "store").identity(config, faster) != identity
    why = RunStore(tmp_path / "store").explain(config, faster)
    assert "design table differs" in why and "speed_mps" in why


def test_a_refused_store_says_what_differs_and_meta_names_the_computing_revision(
        quick_local, default_design_table):
    import dataclasses

    from drake_cert.experiments.run_store import RunStore

    store = RunStore(quick_local / "store")
    why = store.explain(dataclasses.replace(ReproduceConfig.quick(), n=300),
                        default_design_table.designs)
    assert "n 200 there, 300 here" in why
    meta = json.loads((quick_local / "meta.json").read_text())
    assert "git_revision" not in meta
    assert meta["computed_by_revisions"] == [store.revision]
    assert meta["written_by_revision"] == store.revision


def test_a_store_begun_in_other_bf16_digits_is_not_finished_here(default_design_table,
                                                                 tmp_path):
    """Native and emulated bf16 agree on discrete outcomes but not on every digit: resuming
    would mix them, so the store is refused with the reason; --from-store computes nothing."""
    import dataclasses

    from drake_cert.errors import ConfigError
    from drake_cert.experiments.run_store import MANIFEST, RunStore

    config = dataclasses.replace(ReproduceConfig.quick(), precision="bf16")
    store = RunStore(tmp_path / "store")
    identity = store.identity(config, default_design_table.designs)
    store.put_betas(identity, {})
    store.check_arithmetic(identity, "bf16")  # same CPU: fine
    manifest = json.loads((tmp_path / "store" / MANIFEST).read_text())
    here = manifest[identity]["arithmetic"]["numbers"]
    other = "bf16-emulated" if here == "bf16-native" else "bf16-native"
    manifest[identity]["arithmetic"]["numbers"] = other
    (tmp_path / "store" / MANIFEST).write_text(json.dumps(manifest))
    with pytest.raises(ConfigError, match="made in bf16 .* this CPU"):
        RunStore(tmp_path / "store").check_arithmetic(identity, "bf16")


@pytest.mark.slow  # 10 s on 2 cores with the design table cached, more without
def test_the_committed_default_run_is_rewritten_byte_for_byte_from_its_store(tmp_path):
    """results/paper's tables, claims and frames come back byte for byte from its store alone
    (--from-store computes nothing: a refused identity or a missing frame fails here)."""
    import shutil

    paper = Path(__file__).resolve().parents[1] / "results" / "paper"
    shutil.copytree(paper / "store", tmp_path / "store")
    assert main(["reproduce", "--from-store", "--precision", "fp32", "--no-plots",
                 "--out", str(tmp_path)]) == 0
    for name in ("frames.csv", "results.csv", "tables.md", "claims.md", "claims.json"):
        assert (tmp_path / name).read_bytes() == (paper / name).read_bytes(), name


def test_the_cpu_ledger_sums_each_stage_over_invocations_and_identities_apart(tmp_path):
    from drake_cert.experiments.run_store import RunStore

    store = RunStore(tmp_path / "store")
    assert store.cpu("a") == {}  # a store made before the ledger
    store.add_cpu("a", "frames", 10.04)
    RunStore(tmp_path / "store").add_cpu("a", "frames", 5.0)  # a later invocation
    store.add_cpu("a", "calibration_h", 2.5)
    store.add_cpu("b", "frames", 99.0)
    assert RunStore(tmp_path / "store").cpu("a") == dict(
        frames=15.0, frames_parts=2, calibration_h=2.5, calibration_h_parts=1, all=17.5)
