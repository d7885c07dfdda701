"""Combined decisions that a few wrong frames cannot turn against the truth (DESIGN 6.3).

Pure functions on label spans, used by the longitudinal block's speed profile
(:meth:`drake_cert.systems.longitudinal.SpeedProfile.with_combined_decision`).

Vocabulary. Labels are numbered in the preset's friction order; a decision's label range is a
*span* ``(lo, hi)`` of label numbers (contiguous); the whole family ``(0, K - 1)`` is the
envelope (an abstention, a bad frame). A *look* is ``(position_m, span)``: the decision of one
frame about the road condition at its look point. A frame is *right* when the condition at its
look point lies in its span; an abstention is always right.

World assumption: no interior stretch of one road condition is as short as ``window_m``
(the scenario's ``min_condition_length_m``, checked against the route before driving).

Rule (:func:`tolerant_span`). For the road between two consecutive look points, take the
informative looks (span narrower than the envelope) at or before its start (``left``) and at or
after its end (``right``), up to :data:`PER_SIDE` on each side, the nearest first; a *pair* is one
look of each side less than ``window_m`` apart. For a set E of looks, ``M_E`` is the
intersection of the hulls of the pairs that avoid E (the envelope if no pair does). The stretch
gets the hull of every non-empty ``M_E`` over the sets E of at most ``tolerance`` looks; the
envelope when all are empty (more than ``tolerance`` looks are wrong: the frames contradict
each other beyond what the rule tolerates).

Guarantee: if at most ``tolerance`` of the looks used are wrong, the condition at every point
of the stretch lies in its span; as newer looks arrive a stretch's span only narrows or stays,
except for the envelope of a detected contradiction. Proofs: DESIGN 6.3.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence

Span = tuple[int, int]
Look = tuple[float, Span]

PER_SIDE = 4  # informative looks used on each side of a stretch (the nearest)


def hull(a: Span, b: Span) -> Span:
    """The smallest span holding both spans."""
    return (min(a[0], b[0]), max(a[1], b[1]))


def is_within(inner: Span, outer: Span) -> bool:
    """Every label of ``inner`` lies in ``outer``."""
    return outer[0] <= inner[0] and inner[1] <= outer[1]


def tolerant_span(left: Sequence[Look], right: Sequence[Look], *, window_m: float,
                  tolerance: int, full: Span) -> Span:
    """The span of the road between the last look of ``left`` and the first of ``right``
    (module docstring): it holds the condition there whenever at most ``tolerance`` of the
    looks it uses are wrong.

    ``left``: looks at or before the stretch, ``right``: at or after it, each the nearest
    first; abstentions (span ``full``) are skipped, at most :data:`PER_SIDE` informative looks a
    side are used. ``full``: the envelope's span ``(0, K - 1)``.
    """
    a_side = [lk for lk in left if lk[1] != full][:PER_SIDE]
    b_side = [lk for lk in right if lk[1] != full][:PER_SIDE]
    pairs = [(i, len(a_side) + j, hull(a[1], b[1]))
             for i, a in enumerate(a_side) for j, b in enumerate(b_side)
             if b[0] - a[0] < window_m]
    used = sorted({p[0] for p in pairs} | {p[1] for p in pairs})
    lo, hi, found = full[1] + 1, full[0] - 1, False
    for size in range(min(tolerance, len(used)) + 1):
        for removed in itertools.combinations(used, size):
            m_lo, m_hi = full
            for i, j, (h_lo, h_hi) in pairs:
                if i not in removed and j not in removed:
                    m_lo, m_hi = max(m_lo, h_lo), min(m_hi, h_hi)
            if m_lo <= m_hi:  # M_E is not empty: E may be the set of wrong looks
                lo, hi, found = min(lo, m_lo), max(hi, m_hi), True
    return (lo, hi) if found else full


def stretch_spans(looks: Sequence[Look], *, window_m: float, tolerance: int, full: Span,
                  first: int = 0) -> list[tuple[float, Span]]:
    """``(start_m, span)`` of the road from each distinct look point (from the ``first``-th
    distinct one on) to the next, by :func:`tolerant_span`; the road from the last look point
    on, which no later frame has bounded, gets the envelope when ``tolerance`` > 0 (one frame
    alone narrows nothing) and the last look's span at that point with tolerance 0.

    ``looks`` sorted by position (ties: frames of one look point, the car at rest).
    """
    positions = sorted({lk[0] for lk in looks})
    out = []
    for k in range(max(first, 0), len(positions) - 1):
        start, end = positions[k], positions[k + 1]
        left = [lk for lk in reversed(looks) if lk[0] <= start]
        right = [lk for lk in looks if lk[0] >= end]
        out.append((start, tolerant_span(left, right, window_m=window_m, tolerance=tolerance,
                                         full=full)))
    if positions and len(positions) - 1 >= first:
        last = positions[-1]
        at_last = [lk[1] for lk in looks if lk[0] == last]
        span = full
        if tolerance == 0:  # the frames at the last look point, each assumed right
            span = (max(s[0] for s in at_last), min(s[1] for s in at_last))
            span = span if span[0] <= span[1] else full
        out.append((last, span))
    return out
