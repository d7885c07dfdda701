"""Combined decisions that a few wrong frames cannot turn against the truth (docs/design.md
6.3).

Pure functions on label spans, used by the longitudinal block's speed profile
(:meth:`drake_cert.systems.longitudinal.SpeedProfile.with_combined_decision`).

Vocabulary. Labels are numbered in the preset's friction order; a decision's label range is a
*span* ``(lo, hi)`` of label numbers (contiguous); the whole family ``(0, K - 1)`` is the
envelope (an abstention, a bad frame). A *look* is ``(position_m, span)``: the decision of one
camera tick about the road condition at its look point. A look *supports* every label of its
span; it is *right* when the condition at its look point lies in its span (an abstention is
always right).

World assumption: no interior stretch of one road condition is as short as ``window_m``
(the scenario's ``min_condition_length_m``, checked against the route before driving).

Counting rule (:func:`counted_span`). The road between two consecutive look points
``start < end`` (gap g) is bounded by two *sides*: the ticks whose look point lies at or before
``start`` and less than ``(window_m - g) / 2`` behind it (the nearest first), and those at or
after ``end`` and less than ``(window_m - g) / 2`` beyond it (the nearest first), at most
``looks_per_side`` each, abstentions included. Every look of both sides and the stretch then
lie in less than ``window_m`` of road, so at most one condition boundary among them. A side of
q looks keeps the labels that at least ``q - tolerance`` of its looks support; the stretch gets
the hull of the labels either side keeps (the envelope if neither keeps any: the looks
contradict each other beyond the tolerance).

Guarantee: if neither side holds more than ``tolerance`` wrong looks, the condition at every
point of the stretch lies in its span. A side is a run of consecutive camera ticks, so the
drive's failure event is "some run of ``looks_per_side`` consecutive ticks holds more than
``tolerance`` wrong looks" (:func:`run_failure_bound`). As newer looks arrive a stretch's span
only narrows or stays. Proofs: docs/design.md 6.3.
"""

from __future__ import annotations

import bisect
from collections.abc import Sequence

Span = tuple[int, int]
Look = tuple[float, Span]

LOOKS_PER_SIDE = 20  # default most looks a side (the scenario's looks_per_side)


def hull(a: Span, b: Span) -> Span:
    """The smallest span holding both spans."""
    return (min(a[0], b[0]), max(a[1], b[1]))


def is_within(inner: Span, outer: Span) -> bool:
    """Every label of ``inner`` lies in ``outer``."""
    return outer[0] <= inner[0] and inner[1] <= outer[1]


def side_keeps(side: Sequence[Look], *, tolerance: int, full: Span) -> set[int]:
    """The labels that at least ``len(side) - tolerance`` of the side's looks support (every
    label when the side has at most ``tolerance`` looks)."""
    need = len(side) - tolerance
    if need <= 0:
        return set(range(full[0], full[1] + 1))
    return {lab for lab in range(full[0], full[1] + 1)
            if sum(1 for _, (lo, hi) in side if lo <= lab <= hi) >= need}


def counted_span(left: Sequence[Look], right: Sequence[Look], *, tolerance: int,
                 full: Span) -> Span:
    """The span of the road between the looks of ``left`` (at or before it) and ``right`` (at
    or after it), each side already cut to its window and ``looks_per_side`` (module
    docstring): the hull of the labels either side keeps, the envelope if none is kept. It
    holds the condition there whenever neither side holds more than ``tolerance`` wrong
    looks."""
    kept = side_keeps(left, tolerance=tolerance, full=full) | \
        side_keeps(right, tolerance=tolerance, full=full)
    return (min(kept), max(kept)) if kept else full


def stretch_spans(looks: Sequence[Look], *, window_m: float, tolerance: int, full: Span,
                  looks_per_side: int = LOOKS_PER_SIDE,
                  first: int = 0) -> list[tuple[float, Span]]:
    """``(start_m, span)`` of the road from each distinct look point (from the ``first``-th
    distinct one on) to the next, by :func:`counted_span` over the sides of the module
    docstring; the road from the last look point on, which no later frame has bounded, gets the
    envelope when ``tolerance`` > 0 and the last look's span at that point with tolerance 0.

    ``looks`` sorted by position, ties in time order (frames of one look point, the car at
    rest), so that each side is a run of consecutive ticks.
    """
    positions = sorted({lk[0] for lk in looks})
    at = [lk[0] for lk in looks]  # sorted: each side is a slice found by bisection
    out = []
    for k in range(max(first, 0), len(positions) - 1):
        start, end = positions[k], positions[k + 1]
        half = 0.5 * (window_m - (end - start))
        stop = bisect.bisect_right(at, start)  # looks at or before start: looks[:stop]
        left = looks[max(bisect.bisect_right(at, start - half), stop - looks_per_side):stop]
        begin = bisect.bisect_left(at, end)  # looks at or after end: looks[begin:]
        right = looks[begin:min(bisect.bisect_left(at, end + half), begin + looks_per_side)]
        span = counted_span(left, right, tolerance=tolerance, full=full) \
            if half > 0 and left and right else full
        out.append((start, span))
    if positions and len(positions) - 1 >= first:
        last = positions[-1]
        at_last = [lk[1] for lk in looks if lk[0] == last]
        span = full
        if tolerance == 0:  # the frames at the last look point, each assumed right
            span = (max(s[0] for s in at_last), min(s[1] for s in at_last))
            span = span if span[0] <= span[1] else full
        out.append((last, span))
    return out


def run_failure_bound(miss_per_look: float, looks_per_side: int, tolerance: int) -> float:
    """``P(Bin(looks_per_side, miss_per_look) > tolerance)``: for any run of
    ``looks_per_side`` consecutive camera ticks, a bound on the probability that more than
    ``tolerance`` of them are wrong, when each tick is wrong with probability at most
    ``miss_per_look`` given everything before it (docs/design.md 6.2: the coupling argument;
    which ticks the car takes, and where they look, may depend on its earlier decisions)."""
    from scipy.stats import binom

    if not 0.0 <= miss_per_look <= 1.0:
        raise ValueError(f"miss_per_look = {miss_per_look!r} must be in [0, 1]")
    return float(binom.sf(int(tolerance), int(looks_per_side), float(miss_per_look)))
