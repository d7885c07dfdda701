"""Sequential decisions at a known budget (docs/design.md, "Decisions at a known budget"):
sound at any stopping time, cheap on clear frames, consistent with the fixed-n certificate.

The base models here are analytic: a frame's first pixel u decides the label, so under
Gaussian noise of level sigma each label's probability is exact (Phi of a margin over sigma)
and so is the radius the decision may claim.
"""

import math

import numpy as np
import pytest
import torch
from hypothesis import example, given
from hypothesis import strategies as st
from scipy.stats import binom, norm

from drake_cert.certification.classifier import SmoothedClassifier, sequential_radius
from drake_cert.certification.regressor import MedianSmoothedRegressor
from drake_cert.certification.statistics import (
    SequentialOptions,
    beta_mixture_bounds,
    look_plan,
)
from drake_cert.errors import CertificationError

SIGMA, EPS = 0.25, 0.25
FRAME = torch.full((1, 2, 2), 0.5)  # u = 0.5 at the frame


class Thresholds(torch.nn.Module):
    """Label l when u - 0.5 falls between cuts[l] and cuts[l - 1] (cuts descending), u the
    first pixel: label 0 above cuts[0], then 1, ... The label's probability at the frame is
    ``Phi(upper/sigma) - Phi(lower/sigma)`` of its window shifted by -shift."""

    def __init__(self, cuts, shift=0.0):
        super().__init__()
        self.cuts = torch.tensor(cuts)
        self.shift = shift

    def forward(self, z):
        u = z[:, 0, 0, 0] - 0.5 + self.shift
        label = (u[:, None] < self.cuts[None, :]).sum(dim=1)
        return torch.nn.functional.one_hot(label, len(self.cuts) + 1).float()


def two_class(margin):
    """Label 0 with probability Phi(margin / sigma): the true radius of label 0 is margin."""
    return SmoothedClassifier(Thresholds([0.0], shift=margin), 2, SIGMA)


def share_that_certify(margin, alpha, trials, n_max=1000, bound="looks"):
    g = two_class(margin)
    return sum(g.decide(FRAME, EPS, alpha, n_max, 1000, seed=s,
                        options=SequentialOptions(bound=bound)).certified
               for s in range(trials))


@pytest.mark.parametrize("bound", ["looks", "mixture"])
@pytest.mark.parametrize("ratio", [0.9, 0.97])
def test_type_one_error_is_at_most_alpha_when_the_true_radius_is_just_below_eps(ratio, bound):
    alpha, trials = 0.05, 2000
    certified = share_that_certify(ratio * EPS, alpha, trials, bound=bound)
    # Passes with probability 0.995 if the rate is alpha; at 1.5 alpha it would fail with
    # probability ~0.98 (the count's mean 150 lies 2.1 sd above this bound).
    assert certified <= binom.ppf(0.995, trials, alpha), certified


@pytest.mark.parametrize("bound", ["looks", "mixture"])
def test_a_clear_frame_is_decided_in_few_samples(bound):
    g = two_class(2 * EPS)  # true radius 2 eps: p_A = Phi(2) = 0.977
    runs = [g.decide(FRAME, EPS, 0.001, 1100, 1000, seed=s,
                     options=SequentialOptions(bound=bound)) for s in range(200)]
    assert all(r.certified and r.labels == (0,) for r in runs)
    assert np.mean([r.samples for r in runs]) < 200
    assert all(r.radius > EPS and r.reason == "certified" for r in runs)


def test_a_hopeless_frame_stops_for_futility_well_before_n_max():
    g = two_class(0.02)  # label 0 by a hair (p_A = 0.53): far from radius eps
    runs = [g.decide(FRAME, EPS, 0.001, 5000, 1000, seed=s) for s in range(20)]
    assert not any(r.certified for r in runs)
    assert all(r.reason == "futile" and r.labels == () for r in runs)
    assert max(r.samples for r in runs) < 500


def test_decide_agrees_with_the_fixed_n_certificate_on_clear_cases():
    for margin, expect in [(2.5 * EPS, True), (0.3 * EPS, False)]:
        g = two_class(margin)
        fixed = g.certify(FRAME, 100, 10_000, 0.001, 1000, seed=3)
        seq = g.decide(FRAME, EPS, 0.001, 10_000, 1000, seed=4)
        assert (fixed.radius > EPS) == expect == seq.certified
        if seq.certified:  # the sequential radius is a (looser) bound on the same quantity
            assert EPS < seq.radius <= margin


def test_a_label_range_is_certified_where_its_top_label_alone_is_not():
    # Labels 0 | 1 | 2 with cuts at +0.05 and -0.6: at the frame labels 0 and 1 share most
    # mass (0.53 / 0.46), label 2 is far. {0} cannot be certified at eps; {0, 1} can.
    model = Thresholds([0.05, -0.6], shift=0.07)
    g = SmoothedClassifier(model, 3, SIGMA)
    p0 = 1 - norm.cdf((0.05 - 0.07) / SIGMA)
    p01 = 1 - norm.cdf((-0.6 - 0.07) / SIGMA)
    exact = 0.5 * SIGMA * (norm.ppf(p0) + norm.ppf(p01))
    assert exact > EPS and norm.ppf(p0) * SIGMA < EPS
    runs = [g.decide(FRAME, EPS, 0.001, 4000, 1000, ranges=lambda a: [(a,), (0, 1)], seed=s)
            for s in range(20)]
    assert all(r.top_label == 0 for r in runs)  # the noise-free base label
    assert all(r.certified and r.labels == (0, 1) for r in runs)
    assert all(r.radius <= exact for r in runs)  # never more than the exact bound allows


def test_fixed_ranges_need_no_top_label_and_certify_through_their_best_label():
    # The base model's noise-free label is 0, but label 0 is a narrow band |u| < 0.05, so
    # under noise label 1 dominates (P = 0.84): testing every range at once certifies {1}
    # without choosing a label; choosing the noise-free label would have tested {0} alone.
    class Band(torch.nn.Module):
        def forward(self, z):
            u = z[:, 0, 0, 0] - 0.5
            label = torch.where(u.abs() < 0.05, 0, torch.where(u > -0.9, 1, 2))
            return torch.nn.functional.one_hot(label, 3).float()

    g, eps = SmoothedClassifier(Band(), 3, SIGMA), 0.1
    assert g.base_label(FRAME) == 0
    d = g.decide(FRAME, eps, 0.001, 2000, 1000, [(0,), (1,), (2,), (0, 1), (1, 2)], seed=1)
    assert d.certified and d.labels == (1,) and d.top_label == 1
    by_base = g.decide(FRAME, eps, 0.001, 2000, 1000, None, seed=1)  # {0} alone: hopeless
    assert not by_base.certified and by_base.reason == "futile"


def test_selection_samples_are_counted_and_come_from_their_own_stream():
    g = two_class(2 * EPS)
    a = g.decide(FRAME, EPS, 0.001, 1000, 1000, seed=1,
                 options=SequentialOptions(selection_n=16, selection_seed=9))
    b = g.decide(FRAME, EPS, 0.001, 1000, 1000, seed=1)
    assert a.selection_samples == 16 and a.samples == b.samples + 16
    assert (a.counts == b.counts).all()  # the estimation stream is the same


def test_same_seed_same_decision():
    g = two_class(1.1 * EPS)
    a, b = (g.decide(FRAME, EPS, 0.01, 3000, 1000, seed=7) for _ in range(2))
    assert (a.certified, a.samples, a.radius) == (b.certified, b.samples, b.radius)


def test_confidence_sequence_holds_at_every_time_with_probability_at_least_1_minus_alpha():
    rng = np.random.default_rng(0)
    alpha, p, paths, steps = 0.1, 0.7, 400, 300
    draws = rng.random((paths, steps)) < p
    successes = np.cumsum(draws, axis=1)
    looks = np.unique(np.geomspace(1, steps, 40).astype(int))
    missed = 0
    for path in successes:
        for t in looks:
            low, up = beta_mixture_bounds(int(path[t - 1]), int(t), alpha)
            if not low <= p <= up:
                missed += 1
                break
    assert missed <= binom.ppf(0.995, paths, alpha)


def test_confidence_sequence_ends_are_exact_where_closed_form():
    # S = t = 1: M(p) = 1 / (2p) < 1/alpha  <=>  p > alpha/2.
    low, up = beta_mixture_bounds(1, 1, 0.5)
    assert low == pytest.approx(0.25, abs=1e-9) and up == 1.0
    # S = 0 mirrors S = t.
    assert beta_mixture_bounds(0, 10, 0.01) == pytest.approx(
        tuple(1 - v for v in beta_mixture_bounds(10, 10, 0.01)[::-1]))


def test_sequential_radius_is_cohens_for_a_single_label():
    assert sequential_radius(0.9, 0.9, 0.5) == pytest.approx(0.5 * norm.ppf(0.9))
    assert sequential_radius(0.4, 0.4, 0.5) == 0.0


@given(st.lists(st.floats(0.0, 1.0), min_size=2, max_size=6),
       st.lists(st.booleans(), min_size=6, max_size=6))
@example([0.5, 0.5, 0.5], [False, True, True, False, False, False])  # a tie at exactly 2/3
def test_a_range_holding_more_than_k_over_k_plus_1_of_the_mass_holds_the_best_label(weights,
                                                                                   chosen):
    """The premise of the mass radius: wherever a set T of k labels keeps a mass above
    k/(k+1), the best label lies in T. (Within the radius T keeps it, by the 1/sigma-Lipschitz
    PhiInv of the smoothed indicator of T.)"""
    q = np.asarray(weights) + 1e-9
    q = q / q.sum()
    members = [i for i in range(len(q)) if chosen[i]]
    others = [i for i in range(len(q)) if not chosen[i]]
    k = len(members)
    if k and others and q[members].sum() > k / (k + 1) + 1e-12:  # strictly (float rounding)
        assert q[members].max() > q[others].max()


def test_a_range_whose_mass_is_split_between_two_labels_gets_the_mass_radius():
    # p(sunny) >= 0.52, p({sunny, rain}) >= 0.97 at sigma = 1: the label radius is 0.96, the
    # mass radius sigma (PhiInv(0.97) - PhiInv(2/3)) = 1.45: certified at eps = 1
    label = 0.5 * (norm.ppf(0.52) + norm.ppf(0.97))
    mass = norm.ppf(0.97) - norm.ppf(2 / 3)
    assert sequential_radius(0.52, 0.97, 1.0, size=2) == pytest.approx(max(label, mass))
    assert label < 1.0 < mass
    # one dominant label: the label radius is the larger, and is kept
    assert sequential_radius(0.96, 0.97, 1.0, size=2) == pytest.approx(
        0.5 * (norm.ppf(0.96) + norm.ppf(0.97)))
    # one label: the two radii coincide (Cohen's)
    assert sequential_radius(0.9, 0.9, 1.0, size=1) == pytest.approx(norm.ppf(0.9))


def test_looks_are_fixed_in_advance_and_split_alpha_over_the_certifying_ones():
    p0 = norm.cdf(1.0)  # eps = sigma
    plan = look_plan(300, 0.001, 2, threshold=p0)
    assert plan.looks == (53, 106, 212, 300) and plan.certify_from == 53
    assert plan.level == pytest.approx(0.001 / (2 * 4))
    # The first certifying look is the fewest unanimous votes that can certify at that level.
    assert plan.level ** (1 / 53) > p0 >= plan.level ** (1 / 52)
    # A large n_min leaves room for futility-only looks, which spend no alpha.
    far = look_plan(20_000, 0.001, 1, threshold=norm.cdf(2.5),
                    options=SequentialOptions(first_look=32))
    early = [n for n in far.looks if n < far.certify_from]
    assert early and far.bounds(early[0], early[0])[0] == 0.0  # cannot certify there
    assert far.level == pytest.approx(0.001 / (len(far.looks) - len(early)))
    mixture = look_plan(1000, 0.001, 2, batch_size=256,
                        options=SequentialOptions(bound="mixture", first_look=32))
    assert mixture.looks == (32, 96, 224, 480, 736, 992, 1000)
    assert mixture.level == pytest.approx(0.0005)
    with pytest.raises(CertificationError, match="bound"):
        look_plan(100, 0.001, 1, options=SequentialOptions(bound="peek"))
    with pytest.raises(CertificationError, match="never certify"):
        look_plan(300, 0.001, 1, threshold=norm.cdf(3.0))


@pytest.mark.parametrize("kwargs, match", [
    (dict(eps=-1.0), "eps"), (dict(n_max=0), "n_max"), (dict(alpha=1.5), "alpha"),
    (dict(ranges=lambda a: [(1,)]), "containing"), (dict(ranges=lambda a: []), "no candidate"),
    (dict(ranges=[(0, 5)]), "within"),
    (dict(ranges=[(0,)], options=SequentialOptions(selection_n=5)), "selection_n"),
    (dict(options=SequentialOptions(selection_n=-3)), "selection_n"),
    (dict(options=SequentialOptions(bound="fixed")), "bound"),
])
def test_bad_arguments_raise_certification_error(kwargs, match):
    args = dict(x=FRAME, eps=EPS, alpha=0.001, n_max=100, batch_size=100) | kwargs
    with pytest.raises(CertificationError, match=match):
        two_class(EPS).decide(**args)


class Shifted(torch.nn.Module):
    """A regressor whose output under noise is N(centre, (scale sigma)^2): u scaled."""

    def __init__(self, centre, scale):
        super().__init__()
        self.centre, self.scale = centre, scale

    def forward(self, z):
        return (self.centre + self.scale * (z[:, 0, 0, 0] - 0.5))[:, None]


def test_median_decision_certifies_an_interval_that_holds_the_quantiles():
    # y ~ N(50k, (1k)^2) at the frame; at eps = sigma the quantiles Phi(+-1) are 50k -+ 1k.
    h = MedianSmoothedRegressor(Shifted(50_000.0, 4_000.0), SIGMA)
    wide = [(45_000.0, 55_000.0)]
    tight = [(49_500.0, 50_500.0)]  # inside the quantiles: must not be certified
    d = h.decide(FRAME, EPS, 0.001, 4000, 1000, lambda v: tight + wide, seed=2)
    assert d.certified and d.interval == wide[0] and d.index == 1
    assert d.base_value == pytest.approx(50_000.0)
    assert d.samples < 400
    # the point estimate: the median of the outputs drawn (standard error about 1.25 x 1k /
    # sqrt(samples) < 90 N/rad here)
    assert abs(d.sample_median - 50_000.0) < 500.0
    none = h.decide(FRAME, EPS, 0.001, 4000, 1000, lambda v: tight, seed=2)
    assert not none.certified and none.reason == "futile" and none.interval is None


def test_median_decision_type_one_error_is_at_most_alpha():
    # The upper quantile at eps sits at 50k + 1k; an interval ending at 50k + 0.97k is wrong.
    h = MedianSmoothedRegressor(Shifted(50_000.0, 4_000.0), SIGMA)
    alpha, trials = 0.05, 600
    bad = [(40_000.0, 50_970.0)]
    certified = sum(h.decide(FRAME, EPS, alpha, 2000, 1000, lambda v: bad, seed=s).certified
                    for s in range(trials))
    assert certified <= binom.ppf(0.995, trials, alpha)
    assert math.isfinite(certified)
