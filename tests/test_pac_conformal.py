"""The calibration-conditional, per-stiffness-bin thresholds (docs/design.md 3.6): the claims of
drake_cert.certification.pac_conformal, checked on distributions we know."""

import math

import numpy as np
import pytest
from scipy.stats import beta as beta_dist

from drake_cert.certification.conformal import TrueLabelVotes, pac_calibration_from_counts
from drake_cert.certification.pac_conformal import (
    PacTargets,
    bin_edges,
    bin_index,
    min_frames_per_bin,
    order_statistic_miss_bound,
    pac_binned_thresholds,
    pac_order_index,
)
from drake_cert.errors import CertificationError


def test_the_kth_smallest_of_m_scores_is_exceeded_below_by_at_most_its_beta_quantile():
    # Continuous scores: G(r_(k)) ~ Beta(k, m - k + 1) exactly; the bound is its 1 - delta
    # quantile, so over many calibrations G(r_(k)) exceeds it in about a delta share.
    rng = np.random.default_rng(3)
    m, k, delta = 200, 6, 0.05
    bound = order_statistic_miss_bound(k, m, delta)
    assert bound == pytest.approx(beta_dist.ppf(1 - delta, k, m - k + 1))
    g = np.sort(rng.random((20000, m)), axis=1)[:, k - 1]  # uniform scores: G(t) = t
    exceed = float(np.mean(g > bound))
    assert exceed <= delta + 3 * math.sqrt(delta * (1 - delta) / 20000)
    assert exceed >= delta - 3 * math.sqrt(delta * (1 - delta) / 20000)  # not vacuous


def test_the_bound_holds_for_scores_with_atoms():
    # Monte Carlo scores take few values (a Clopper-Pearson bound of integer votes): ties at
    # the threshold only make a strict miss rarer.
    rng = np.random.default_rng(4)
    values = np.array([0.0, 0.1, 0.2, 0.5, 0.9])
    probs = np.array([0.02, 0.03, 0.05, 0.3, 0.6])
    m, k, delta = 150, 4, 0.1
    bound = order_statistic_miss_bound(k, m, delta)
    cdf_strict = {v: float(probs[values < v].sum()) for v in values}  # G(t) = P(score < t)
    draws = rng.choice(values, p=probs, size=(20000, m))
    g = np.array([cdf_strict[v] for v in np.sort(draws, axis=1)[:, k - 1]])
    assert float(np.mean(g > bound)) <= delta


def test_the_order_index_is_the_largest_whose_bound_meets_the_target():
    for m, target, delta in [(500, 0.1, 1e-3 / 12), (50, 0.2, 0.01), (2000, 0.05, 1e-4)]:
        k = pac_order_index(m, target, delta)
        assert k >= 1
        assert order_statistic_miss_bound(k, m, delta) <= target
        assert order_statistic_miss_bound(k + 1, m, delta) > target
    assert pac_order_index(5, 0.1, 1e-3) == 0  # too few frames: threshold 0


def test_min_frames_per_bin_is_the_edge_where_a_threshold_appears():
    for target, delta in [(0.1, 1e-3 / 12), (0.05, 1e-4), (0.2, 0.01)]:
        m = min_frames_per_bin(target, delta)
        assert pac_order_index(m, target, delta) == 1
        assert pac_order_index(m - 1, target, delta) == 0


def test_bins_cover_the_interval_and_its_ends():
    edges = bin_edges(80e3, 120e3, 4)
    assert edges.tolist() == [80e3, 90e3, 100e3, 110e3, 120e3]
    assert bin_index(np.array([80e3, 89999.0, 90e3, 119e3, 120e3]), edges).tolist() == \
        [0, 0, 1, 3, 3]
    with pytest.raises(CertificationError, match="bins"):
        bin_edges(0.0, 1.0, 0)


def _edge_heavy_scores(rng, frames_per_label, intervals):
    """Scores whose low tail sits in each label's lowest-stiffness bin (as g's does near the
    next label), labels and true stiffness uniform in each interval."""
    labels, stiffness, scores = [], [], []
    for lab, (lo, hi) in enumerate(intervals):
        c = rng.uniform(lo, hi, frames_per_label)
        edge = (c - lo) / (hi - lo) < 0.25
        s = np.where(edge, rng.beta(2.0, 2.0, frames_per_label), rng.beta(20.0, 2.0,
                                                                         frames_per_label))
        labels.append(np.full(frames_per_label, lab))
        stiffness.append(c)
        scores.append(s)
    return np.concatenate(scores), np.concatenate(labels), np.concatenate(stiffness)


def test_every_stiffness_bin_misses_within_its_bound_where_a_label_average_does_not():
    # The label-wide threshold at the same target leaves the edge bin missing 3x as often;
    # the binned threshold (the least of the bins') keeps every bin within the bound.
    rng = np.random.default_rng(5)
    intervals = [(80e3, 120e3), (40e3, 80e3)]
    scores, labels, stiffness = _edge_heavy_scores(rng, 2000, intervals)
    thresholds, per_bin = pac_binned_thresholds(
        scores, labels, stiffness, intervals,
        targets=PacTargets(bins=4, miss_target=0.1, delta_cal=1e-3))
    test_s, test_l, test_c = _edge_heavy_scores(rng, 40000, intervals)
    for lab, (lo, hi) in enumerate(intervals):
        rows = per_bin[lab]
        assert thresholds[lab] == min(r.threshold for r in rows)
        which = bin_index(test_c[test_l == lab], bin_edges(lo, hi, 4))
        for b, row in enumerate(rows):
            miss = float(np.mean(test_s[test_l == lab][which == b] < thresholds[lab]))
            assert miss <= row.miss_bound <= 0.1, (lab, b, miss, row)
        label_wide = np.sort(scores[labels == lab])[int(0.1 * 2000) - 1]
        edge_miss = float(np.mean(test_s[test_l == lab][which == 0] < label_wide))
        assert edge_miss > 0.25  # the label average hides the edge bin


def test_the_calibration_reports_the_worst_bin_and_names_a_bin_without_frames():
    rng = np.random.default_rng(6)
    intervals = [(80e3, 120e3), (40e3, 80e3), (20e3, 40e3)]
    scores, labels, stiffness = _edge_heavy_scores(rng, 800, intervals)
    counts = np.round(scores * 500).astype(np.int64)
    targets = PacTargets(bins=4, miss_target=0.1, delta_cal=1e-3)
    cal = pac_calibration_from_counts(TrueLabelVotes(counts, labels, stiffness, 500), intervals,
                                      sigma=1.0, targets=targets)
    worst = max(r.miss_bound for rows in cal.bins.values() for r in rows)
    assert cal.alpha_c == worst <= 0.1 and cal.delta_cal == 1e-3
    assert cal.alpha_total == pytest.approx(worst + 0.002)
    again = type(cal).from_json(cal.to_json())
    assert again == cal
    keep = ~((labels == 2) & (stiffness > 35e3))  # snow's grippiest bin left empty
    with pytest.raises(CertificationError, match="'snow', stiffness bin \\[35000, 40000\\]"):
        pac_calibration_from_counts(TrueLabelVotes(counts[keep], labels[keep], stiffness[keep],
                                                   500), intervals, sigma=1.0, targets=targets,
                                    label_names=["sunny", "rain", "snow"])
