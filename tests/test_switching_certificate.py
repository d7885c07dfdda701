"""Switching among a preset's designs (drake_cert.synthesis.switching): what is proved, checked
without the solver that found it, and what verify refuses.

The claims, for the shipped vehicle, conditions and settings:
- with the gains synthesized jointly (the default) every preset's designs share one Lyapunov
  matrix P at a decay rate of at least the settings' alpha: every corner of every design's box
  satisfies the decay LMI (eigenvalues), so the reference loops stay exponentially stable at
  the certified rate under switching every 10 ms with stiffness and speed varying in time; one
  P even serves the whole table;
- with each range's gain synthesized separately, robotcar-like has no common quadratic
  Lyapunov matrix (a dual witness, checked by eigenvalues): its certificate is an
  average-dwell-time one, and a simulation obeying the dwell keeps ``V_sigma`` under the bound
  the argument gives;
- verify rejects a tampered matrix, an inflated decay or dwell, and an uncovered design; a
  file written before certificates existed still loads and verifies, with a note.
"""

import dataclasses
import functools
import math

import numpy as np
import pytest
import scipy.linalg
import yaml

from drake_cert import cli
from drake_cert.dynamics import lateral_error_dynamics
from drake_cert.synthesis import gains, switching
from drake_cert.synthesis.design_io import DesignTable, load_design_file, save_design_table
from drake_cert.synthesis.switching import COMMON, DWELL, design_key, switching_families
from drake_cert.synthesis.verify import SWITCHING, reference_matrix, verify_design_table
from drake_cert.synthesis.verify_switching import (
    SWITCHING_TOLERANCE,
    check_speeds,
    check_switching_certificate,
    check_table_switching,
)

STEP_S = 0.01  # switching period of the simulations (s)
ACCEL_MPS2 = 4.0  # |dV/dt| of the simulations


@pytest.fixture(scope="module")
def certified(certified_design_table) -> DesignTable:
    """The shipped table with its switching certificates (what synthesize --out writes)."""
    return certified_design_table


@pytest.fixture(scope="module")
def separate(default_design_table) -> DesignTable:
    """robotcar-like's designs with each range's own gain LMI (``gains="separate"``), and
    their switching certificate."""
    from drake_cert.synthesis.design_io import with_switching_certificates
    from drake_cert.synthesis.table import synthesize_table

    t = default_design_table
    conditions = dataclasses.replace(
        t.conditions, presets=[p for p in t.conditions.presets if p.name == "robotcar-like"])
    designs = synthesize_table(t.vehicle, conditions, t.settings, gains="separate")
    return with_switching_certificates(dataclasses.replace(t, designs=designs,
                                                           conditions=conditions,
                                                           switching=None))


def _family(table, name):
    return dict(switching_families(table.designs, table.conditions))[name]


def _certificate(table, name):
    return {c.family: c for c in table.switching}[name]


def _speed_min(table):
    return table.settings.synthesis.speed_min_mps


def _closed_loop(table, design, c, v):
    a, b, _ = lateral_error_dynamics(table.vehicle, c, v)
    return a - np.outer(b, design.k_m_array)


def _proved_rate(p, m):
    """Decay rate P proves for M, by plain numpy: P = L L', rate = -lambda_max(L^-1 sym L^-T)/2."""
    l_inv = np.linalg.inv(np.linalg.cholesky(p))
    lyap = m.T @ p + p @ m
    return -0.5 * np.linalg.eigvalsh(l_inv @ (0.5 * (lyap + lyap.T)) @ l_inv.T).max()


def test_the_check_uses_the_gain_grid_checks_tolerance():
    assert SWITCHING_TOLERANCE == gains.GRID_CHECK_TOLERANCE


def test_every_preset_is_certified_and_the_certificates_check(certified):
    methods = {c.family: c.method for c in certified.switching}
    assert methods == {"carla-like": COMMON, "rtk-like": COMMON, "robotcar-like": COMMON,
                       "weather": COMMON}
    assert check_table_switching(certified.vehicle, certified.designs, certified.settings,
                                 certified.conditions, certified.switching,
                                 functools.partial(reference_matrix, certified.vehicle)) == []
    alpha = certified.settings.synthesis.decay_rate
    for c in certified.switching:
        # what the joint LMI asked, up to the solver's accuracy (the stored rate is what the
        # returned matrix proves, recomputed by generalized eigenvalues)
        assert 0.99 * alpha <= c.decay_rate_per_s <= alpha + 0.2
        assert c.dwell_time_s == 0.0 and c.jump_factor == 1.0


@pytest.mark.parametrize("preset", ["carla-like", "rtk-like", "robotcar-like", "weather"])
def test_a_presets_designs_share_a_lyapunov_matrix_checked_at_every_corner(certified, preset):
    cert = _certificate(certified, preset)
    p = np.array(cert.lyapunov_matrix)
    assert np.allclose(p, p.T) and np.linalg.eigvalsh(p).min() == pytest.approx(1.0)
    designs = [d for d in _family(certified, preset) if d.has_safe_speed]
    assert sorted(cert.designs_covered) == sorted(design_key(d) for d in designs)
    tol = gains.GRID_CHECK_TOLERANCE
    for d in designs:
        lo, hi = d.certified_interval
        assert d.speed_mps <= d.gain_speed_max_mps  # the box holds every speed of the design
        for c in (lo, hi):
            for v in (_speed_min(certified), d.gain_speed_max_mps):
                m = _closed_loop(certified, d, c, v)
                lmi = m.T @ p + p @ m + 2.0 * cert.decay_rate_per_s * p
                # symmetrised LMI <= 0 up to the tolerance, measured in P's own scale
                scale = np.linalg.eigvalsh(p).max()
                assert np.linalg.eigvalsh(0.5 * (lmi + lmi.T)).max() <= 2 * tol * scale
                assert _proved_rate(p, m) >= cert.decay_rate_per_s - tol
        # the corners suffice (affine in (C, C/V)); inside the box it holds too
        for c in np.linspace(lo, hi, 5):
            for v in np.linspace(_speed_min(certified), d.gain_speed_max_mps, 5):
                assert _proved_rate(p, _closed_loop(certified, d, c, v)) >= \
                    cert.decay_rate_per_s - tol


def test_one_lyapunov_matrix_serves_the_whole_table(certified):
    """The joint LMI shares X = P^-1 among all designs of the table, not only a preset's."""
    whole = switching.common_lyapunov_certificate(certified.vehicle, certified.designs,
                                                  certified.settings.synthesis)  # no loop part
    assert whole.method == COMMON
    assert whole.decay_rate_per_s >= 0.99 * certified.settings.synthesis.decay_rate


def test_arbitrary_switching_with_time_varying_stiffness_and_speed_decays_at_the_certified_rate(
        certified):
    """s' = (A(C_t, V_t) - b(C_t) k_i(t)) s: a random robotcar-like design every 10 ms, C
    random in its certified interval, V changing at +-4 m/s^2 inside its speed range; exact
    steps."""
    cert = _certificate(certified, "robotcar-like")
    p = np.array(cert.lyapunov_matrix)
    designs = [d for d in _family(certified, "robotcar-like") if d.has_safe_speed]
    rng = np.random.default_rng(7)
    rate = cert.decay_rate_per_s - gains.GRID_CHECK_TOLERANCE
    v_min = _speed_min(certified)
    for _ in range(3):
        mats, v = [], rng.uniform(v_min, 20.0)
        for _ in range(1000):  # 10 s
            d = designs[rng.integers(len(designs))]
            v = float(np.clip(v + rng.choice((-1.0, 1.0)) * ACCEL_MPS2 * STEP_S, v_min,
                              d.gain_speed_max_mps))
            mats.append(_closed_loop(certified, d, rng.uniform(*d.certified_interval), v))
        steps = scipy.linalg.expm(np.array(mats) * STEP_S)  # exact, one per 10 ms
        s = rng.normal(size=4) * np.array([1.0, 0.5, 0.1, 0.1])
        lyap0 = s @ p @ s
        for k, step in enumerate(steps, start=1):
            before = s @ p @ s
            s = step @ s
            after = s @ p @ s
            assert after <= before * math.exp(-2.0 * rate * STEP_S) * (1 + 1e-9)
            assert after <= lyap0 * math.exp(-2.0 * rate * k * STEP_S) * (1 + 1e-8)


def _no_common_p_witness(matrices):
    """Z_k >= 0, sum tr Z_k = 1, with sum (M_k Z_k + Z_k M_k') >= delta I: maximise delta.
    Returns the Z_k projected onto the PSD cone (so the proof below needs no solver)."""
    import cvxpy as cp

    zs = [cp.Variable((4, 4), symmetric=True) for _ in matrices]
    delta = cp.Variable()
    total = sum(m @ z + z @ m.T for m, z in zip(matrices, zs, strict=True))
    problem = cp.Problem(cp.Maximize(delta),
                         [z >> 0 for z in zs] + [sum(cp.trace(z) for z in zs) == 1,
                                                 0.5 * (total + total.T) >> delta * np.eye(4)])
    assert gains.solve_sdp(problem)
    out = []
    for z in zs:
        w, u = np.linalg.eigh(0.5 * (z.value + z.value.T))
        out.append((u * np.clip(w, 0.0, None)) @ u.T)
    return out


def test_separately_synthesized_gains_share_no_quadratic_lyapunov_matrix(separate):
    """If P > 0 had M_k' P + P M_k < 0 at every corner, then for Z_k >= 0 (not all 0)
    0 > sum tr((M_k' P + P M_k) Z_k) = tr(P sum (M_k Z_k + Z_k M_k')), which a witness with
    sum (M_k Z_k + Z_k M_k') > 0 makes positive: no such P (at any decay rate >= 0). This is
    why the gains are synthesized jointly by default."""
    designs = [d for d in _family(separate, "robotcar-like") if d.has_safe_speed]
    matrices = [_closed_loop(separate, d, c, v) for d in designs
                for c in d.certified_interval
                for v in (_speed_min(separate), d.gain_speed_max_mps)]
    zs = _no_common_p_witness(matrices)
    assert all(np.linalg.eigvalsh(z).min() >= -1e-12 for z in zs)  # PSD up to rounding
    assert sum(np.trace(z) for z in zs) > 0.5
    total = sum(m @ z + z @ m.T for m, z in zip(matrices, zs, strict=True))
    assert np.linalg.eigvalsh(0.5 * (total + total.T)).min() > 1e-3
    assert _certificate(separate, "robotcar-like").method == DWELL


def test_joint_gains_cost_no_safe_speed_against_separate_ones(certified, separate):
    """The joint synthesis (gain boxes up to each design's grip speed) keeps every
    robotcar-like safe speed of the separate synthesis within one refinement step."""
    joint = {design_key(d): d.speed_mps for d in _family(certified, "robotcar-like")}
    for d in _family(separate, "robotcar-like"):
        assert joint[design_key(d)] >= d.speed_mps - 0.02, design_key(d)


def test_switching_that_respects_the_dwell_time_stays_under_the_average_dwell_bound(separate):
    """robotcar-like, separate gains: V_sigma(s) = s' P_sigma s falls by exp(-2 lambda_0 t)
    between switches and grows at most by mu at one; switching every 1.2 x dwell_time_s to a
    random design, with C and V moving inside its box every 10 ms, stays under
    mu^N exp(-2 lambda_0 t) V(0)."""
    cert = _certificate(separate, "robotcar-like")
    p_of = {k: np.array(m.lyapunov_matrix) for m in cert.modes for k in m.designs}
    designs = [d for d in _family(separate, "robotcar-like") if d.has_safe_speed]
    rng = np.random.default_rng(3)
    rate = cert.decay_rate_per_s - gains.GRID_CHECK_TOLERANCE
    hold = max(1, round(1.2 * cert.dwell_time_s / STEP_S))
    d = designs[0]
    s = rng.normal(size=4) * np.array([1.0, 0.5, 0.1, 0.1])
    v = 10.0
    lyap0, switches = s @ p_of[design_key(d)] @ s, 0
    steps = round(4 * 1.2 * cert.dwell_time_s / STEP_S)  # four switches
    for k in range(1, steps + 1):
        if k % hold == 0:
            d, switches = designs[rng.integers(len(designs))], switches + 1
        v = float(np.clip(v + rng.choice((-1.0, 1.0)) * ACCEL_MPS2 * STEP_S,
                          _speed_min(separate), d.gain_speed_max_mps))
        s = scipy.linalg.expm(_closed_loop(separate, d, rng.uniform(*d.certified_interval), v)
                              * STEP_S) @ s
        bound = cert.jump_factor ** switches * math.exp(-2.0 * rate * k * STEP_S) * lyap0
        assert s @ p_of[design_key(d)] @ s <= bound * (1 + 1e-8)
    assert switches == 4


def test_every_presets_l1_reference_loops_share_a_matrix_with_the_filter_state(certified):
    """zeta = [s, u - u_ff]: one P_z with M_i' P_z + P_z M_i + 2 lambda_z P_z <= 0 at both ends
    of every design's interval and every speed of a grid between the synthesis's grid speeds
    (the piecewise-constant law, the one that runs; M_i its reference loop on zeta)."""
    from drake_cert.synthesis.loop_switching import loop_matrices, loop_speeds
    from drake_cert.synthesis.switching import certified_rate

    for c in certified.switching:
        assert c.loop_law == "piecewise_constant" and c.loop_decay_rate_per_s > 0.05
        p = np.array(c.loop_lyapunov_matrix)
        designs = _family(certified, c.family)
        # verify's own check (its reference systems, speeds half a step off the synthesis's)
        assert check_switching_certificate(
            certified.vehicle, designs, certified.settings, c,
            functools.partial(reference_matrix, certified.vehicle)) == []
        d = designs[0]
        posed = set(loop_speeds(d, _speed_min(certified)))
        inner = [v for v in check_speeds(d, _speed_min(certified))[1:-1]]
        assert inner and not posed & set(inner)
        for d in designs[:2]:  # a quarter step off both grids
            for m in loop_matrices(certified.vehicle, d, _speed_min(certified), c.loop_law,
                                   offset=0.25):
                assert certified_rate(p, m) >= c.loop_decay_rate_per_s - 1e-6


def test_the_loop_certificate_holds_above_each_safe_speed_by_the_tracking_margin(certified):
    """The car may run up to its speed tracking error above the design's safe speed: the L1
    loops' matrix proves its rate there too, up to the state-feedback box's 1 m/s margin, at
    both interval ends, at speeds the synthesis did not pose its LMI at."""
    from drake_cert.synthesis.loop_switching import (
        LOOP_SPEED_MARGIN_MPS,
        loop_speed_top,
        steering_coordinates,
    )
    from drake_cert.synthesis.switching import certified_rate

    assert LOOP_SPEED_MARGIN_MPS == 1.0
    for c in certified.switching:
        p = np.array(c.loop_lyapunov_matrix)
        for d in _family(certified, c.family):
            top = loop_speed_top(d, _speed_min(certified))
            assert top == pytest.approx(min(d.speed_mps + 1.0, d.gain_speed_max_mps))
            assert top >= d.speed_mps + 0.5  # the gain box reaches V_grip + 1 >= V + 1
            for v in (d.speed_mps + 0.1, d.speed_mps + 0.37, d.speed_mps + 0.61, top):
                for stiffness in d.certified_interval:
                    m = steering_coordinates(reference_matrix(certified.vehicle, d, stiffness, v),
                                             d.k_m)
                    assert certified_rate(p, m) >= c.loop_decay_rate_per_s - 1e-6, (d.labels, v)


def test_verify_rejects_a_tampered_loop_matrix_and_an_inflated_loop_rate(rtk_file, tmp_path,
                                                                         capsys):
    def tamper(certs, raw):
        p = certs["rtk-like"]["loop_lyapunov_matrix"]
        p[4][4] *= 1e4  # still positive definite, no longer a Lyapunov matrix

    _verify_fails(_edited(rtk_file, tmp_path, tamper), capsys, "(rtk-like)",
                  "the loop matrix proves decay")

    def inflate(certs, raw):
        certs["rtk-like"]["loop_decay_rate_per_s"] *= 3.0

    _verify_fails(_edited(rtk_file, tmp_path, inflate), capsys, "the loop matrix proves decay")


def test_verify_rejects_a_loop_rate_claimed_without_its_matrix(rtk_file, tmp_path, capsys):
    def drop(certs, raw):
        del certs["rtk-like"]["loop_lyapunov_matrix"]  # the rate stays: a claim with no proof

    _verify_fails(_edited(rtk_file, tmp_path, drop), capsys, "stores no loop matrix")


def test_the_loop_matrix_is_stated_on_the_state_a_switch_leaves_in_place(certified):
    """A switch keeps s and the steering u (the estimate carried over, systems/l1_law.py), so
    zeta = [s, u - u_ff] is continuous on a straight road: the same z' P_z z before and after,
    although u_ad = u - u_ff + k_m' s jumps with the gain. The certificate's M_i is R_i on zeta."""
    from drake_cert.synthesis.loop_switching import loop_matrices, steering_coordinates

    rng = np.random.default_rng(0)
    for c in certified.switching:
        assert c.loop_lyapunov_matrix is not None
        designs = _family(certified, c.family)
        a, b = designs[0], designs[-1]
        m = loop_matrices(certified.vehicle, a, _speed_min(certified), c.loop_law)[0]
        reference = reference_matrix(certified.vehicle, a, a.certified_interval[0],
                                     _speed_min(certified))
        assert np.allclose(m, steering_coordinates(reference, a.k_m))
        for s in rng.normal(size=(3, 4)):
            u = 0.01 * rng.normal()  # the steering, kept across the switch
            u_ad_a, u_ad_b = u + a.k_m_array @ s, u + b.k_m_array @ s
            assert u_ad_a != pytest.approx(u_ad_b)
            zeta_a = np.append(s, u_ad_a - a.k_m_array @ s)
            zeta_b = np.append(s, u_ad_b - b.k_m_array @ s)
            assert np.allclose(zeta_a, zeta_b)


def test_a_drive_that_switches_every_frame_meets_the_loop_certificate(certified):
    cert = _certificate(certified, "robotcar-like")
    fast = [10.0 + 0.1 * i for i in range(8)] + [11.0 + 0.001 * i for i in range(5)]
    report = switching.drive_switching_report(cert, fast)
    assert report["switching_certificate_met"] is True and "switching_note" not in report
    assert report["loop_switching_decay_per_s"] == cert.loop_decay_rate_per_s > 0


def test_a_loop_matrix_written_for_the_old_state_is_refused_on_load(rtk_file, tmp_path):
    from drake_cert.errors import DesignFormatError

    def old(certs, raw):
        del certs["rtk-like"]["loop_state"]
        certs["rtk-like"]["loop_jump_factor"] = 1.026

    with pytest.raises(DesignFormatError, match="older drake-cert.*synthesize again"):
        load_design_file(_edited(rtk_file, tmp_path, old))


def test_a_drive_that_switches_l1_loops_without_a_common_matrix_is_not_reported_certified(
        certified):
    from drake_cert.cli.synthesize import format_switching
    from drake_cert.systems.driving import drive_warnings

    cert = _certificate(certified, "rtk-like")
    with_loop = switching.drive_switching_report(cert, [1.0, 2.0])
    assert with_loop["switching_certificate_met"] is True and "switching_note" not in with_loop
    bare = dataclasses.replace(cert, loop_lyapunov_matrix=None, loop_decay_rate_per_s=0.0)
    assert switching.drive_switching_report(bare, [])["switching_certificate_met"] is True
    report = switching.drive_switching_report(bare, [1.0, 2.0])
    assert report["switching_certificate_met"] is False
    assert report["loop_switching_decay_per_s"] == 0.0
    assert drive_warnings(report) == [switching.LOOP_MISSING_NOTE]
    gradient = dataclasses.replace(bare, loop_law="gradient")
    report = switching.drive_switching_report(gradient, [1.0])
    assert report["switching_certificate_met"] is False
    assert report["switching_note"] == switching.GRADIENT_LOOP_NOTE
    lines = format_switching([bare, cert]).splitlines()
    assert "NOT certified" in lines[0] and "L1 loops: common matrix" in lines[1]


# ------------------------------------------------------------------ file and verify

@pytest.fixture(scope="module")
def rtk_table(certified) -> DesignTable:
    """The rtk-like designs alone (verify has 6 designs to recompute), certificates computed on
    save (the table embeds its conditions, as synthesize writes it)."""
    keep = {design_key(d) for d in _family(certified, "rtk-like")}
    return dataclasses.replace(certified, designs=[d for d in certified.designs
                                                   if design_key(d) in keep], switching=None)


@pytest.fixture(scope="module")
def rtk_file(rtk_table, tmp_path_factory):
    path = tmp_path_factory.mktemp("switching") / "rtk.yaml"
    save_design_table(path, rtk_table)
    return path


def test_the_certificates_round_trip_through_the_file_and_verify_passes(certified, rtk_file,
                                                                         tmp_path, capsys):
    loaded = load_design_file(rtk_file)
    assert [c.family for c in loaded.switching] == [c.family for c in certified.switching]
    assert _certificate(loaded, "rtk-like") == _certificate(certified, "rtk-like")
    report = verify_design_table(loaded, require_switching=True)
    assert report.ok and report.switching_failures == [] and report.notes == []
    path = tmp_path / "all.yaml"
    save_design_table(path, certified)
    assert load_design_file(path).switching == certified.switching


def _edited(rtk_file, tmp_path, edit):
    raw = yaml.safe_load(rtk_file.read_text())
    edit({c["family"]: c for c in raw["switching"]}, raw)
    path = tmp_path / "tampered.yaml"
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    return path


def _verify_fails(path, capsys, *needles):
    assert cli.main(["verify", str(path), "--no-complete"]) == 1
    err = capsys.readouterr().err
    assert "the design file fails switching" in err
    for needle in needles:
        assert needle in err


def test_verify_rejects_a_tampered_lyapunov_matrix(rtk_file, tmp_path, capsys):
    def edit(certs, raw):
        p = certs["rtk-like"]["lyapunov_matrix"]
        p[0][2] = p[2][0] = p[0][2] * 0.5

    _verify_fails(_edited(rtk_file, tmp_path, edit), capsys, "(rtk-like)", "proves decay")


def test_verify_rejects_an_inflated_decay_rate(rtk_file, tmp_path, capsys):
    def edit(certs, raw):
        certs["rtk-like"]["decay_rate_per_s"] *= 1.2

    _verify_fails(_edited(rtk_file, tmp_path, edit), capsys, "(rtk-like)", "proves decay")


def test_verify_rejects_a_matrix_that_is_not_positive_definite(rtk_file, tmp_path, capsys):
    def edit(certs, raw):
        certs["rtk-like"]["lyapunov_matrix"] = (-np.eye(4)).tolist()

    _verify_fails(_edited(rtk_file, tmp_path, edit), capsys, "not positive definite")


def test_verify_rejects_a_design_the_certificate_does_not_cover(rtk_file, tmp_path, capsys):
    def edit(certs, raw):  # as if the design had been added after the certificate
        certs["rtk-like"]["designs_covered"].remove("cobblestone+sand")

    _verify_fails(_edited(rtk_file, tmp_path, edit), capsys,
                  "cobblestone+sand has a safe speed but is not covered")


def test_an_added_design_outside_every_family_fails(certified, rtk_table):
    extra = dataclasses.replace(_family(certified, "rtk-like")[0], labels=[])  # a regression design
    table = dataclasses.replace(rtk_table, designs=rtk_table.designs + [extra],
                                switching=certified.switching)
    failures = check_table_switching(table.vehicle, table.designs, table.settings,
                                     table.conditions, table.switching,
                                     functools.partial(reference_matrix, table.vehicle))
    assert len(failures) == 1 and "belongs to no switching family" in failures[0]
    # without conditions the family is the whole table: the new design is not covered
    cert = switching.common_lyapunov_certificate(table.vehicle, rtk_table.designs, table.settings)
    assert check_switching_certificate(table.vehicle, table.designs, table.settings, cert,
                                       functools.partial(reference_matrix, table.vehicle)) == [
        f"switching certificate (table): design {design_key(extra)} has a safe speed but is not "
        "covered"]
    assert design_key(extra) == "[40000, 60000]"  # a regression design is named by its interval


def test_dwell_certificates_recheck_the_jump_factor_and_dwell(separate):
    cert = _certificate(separate, "robotcar-like")
    designs = _family(separate, "robotcar-like")
    args = (separate.vehicle, designs, separate.settings)
    own = functools.partial(reference_matrix, separate.vehicle)  # verify's reference loops
    assert check_switching_certificate(*args, cert, own) == []
    shorter = dataclasses.replace(cert, dwell_time_s=0.5 * cert.dwell_time_s)
    assert any("dwell time" in f for f in check_switching_certificate(*args, shorter, own))
    smaller = dataclasses.replace(cert, jump_factor=1.0 + 0.5 * (cert.jump_factor - 1.0))
    assert any("jump factor" in f for f in check_switching_certificate(*args, smaller, own))


def test_a_file_without_certificates_loads_and_verifies_with_a_note(rtk_table, tmp_path):
    path = tmp_path / "old.yaml"
    save_design_table(path, rtk_table, switching=False)
    assert "switching" not in yaml.safe_load(path.read_text())
    old = load_design_file(path)
    assert old.switching is None
    report = verify_design_table(old)
    assert report.ok and len(report.notes) == 1 and "no switching certificate" in report.notes[0]
    strict = verify_design_table(old, require_switching=True)
    assert not strict.ok and strict.switching_failures[0][0] == SWITCHING


def test_the_command_line_fails_a_table_without_certificates_unless_told_not_to(
        rtk_table, tmp_path, capsys):
    path = tmp_path / "old.yaml"
    save_design_table(path, rtk_table, switching=False)
    assert cli.main(["verify", str(path), "--no-complete"]) == 1
    assert "no switching certificate" in capsys.readouterr().err
    assert cli.main(["verify", str(path), "--no-complete", "--no-switching"]) == 0


def test_a_malformed_switching_section_is_refused_naming_the_key(rtk_file, tmp_path):
    from drake_cert.errors import DesignFormatError

    def edit(certs, raw):
        certs["rtk-like"]["lyapunov_matrix"][1] = [1.0, 2.0]

    with pytest.raises(DesignFormatError, match=r"switching\[1\]\.lyapunov_matrix must be a 4 x 4"):
        load_design_file(_edited(rtk_file, tmp_path, edit))


def test_the_chatter_bound_is_the_worst_burst_beyond_one_switch_per_average_dwell():
    from drake_cert.synthesis.switching import chatter_bound

    assert chatter_bound([], 1.0) == 0.0
    assert chatter_bound([3.0], 1.0) == 1.0  # one switch: N(t, T) = 1 on any interval
    assert chatter_bound([0.0, 5.0, 10.0], 1.0) == 1.0  # slower than tau_a: no burst
    assert chatter_bound([0.0, 0.1, 0.2], 1.0) == pytest.approx(3.0 - 0.2)
    # the definition, by brute force over every interval between two switches
    times = np.sort(np.random.default_rng(0).uniform(0.0, 20.0, 15))
    brute = max((j - i + 1) - (times[j] - times[i]) / 2.5
                for i in range(15) for j in range(i, 15))
    assert chatter_bound(times, 2.5) == pytest.approx(brute)


def test_when_the_joint_lmi_is_infeasible_every_range_falls_back_to_its_own_lmi(
        default_design_table):
    """robotcar-like alone at a decay rate of 0.8/s: each range's own gain LMI is feasible, the
    shared one has no solution that certifies (at 0.5/s it has: Clarabel calls it
    optimal_inaccurate and its matrix proves 0.5/s at every corner, so it is kept); the joint
    synthesis then gives exactly the separate design (and the certificate of such designs is
    the average-dwell one, tested above)."""
    from drake_cert.synthesis.table import joint_design_gains, synthesize_label_range

    t = default_design_table
    conditions = dataclasses.replace(
        t.conditions, presets=[p for p in t.conditions.presets if p.name == "robotcar-like"])
    settings = dataclasses.replace(
        t.settings, synthesis=dataclasses.replace(t.settings.synthesis, decay_rate=0.8))
    assert joint_design_gains(t.vehicle, conditions, settings) is None
    joint = synthesize_label_range(t.vehicle, conditions, ["snow"], settings)
    separate = synthesize_label_range(t.vehicle, conditions, ["snow"], settings,
                                      gains="separate")
    assert dataclasses.asdict(joint) == dataclasses.asdict(separate)
    assert joint.gain_speed_max_mps == 30.0  # the separate form's box, not the grip speed's
    from drake_cert.errors import ConfigError

    with pytest.raises(ConfigError, match="gains = 'both' must be one of joint, separate"):
        synthesize_label_range(t.vehicle, conditions, ["snow"], settings, gains="both")
