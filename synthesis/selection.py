"""Which synthesized design a run-time stiffness interval gets (DESIGN 5.4 and 6).

One code path for the Drake diagram's certified-interval block and for the experiments:
a classification interval is a contiguous label range and gets that range's design; the
family envelope's design is the fallback, never a nominal one. (A regression interval gets the
narrowest design holding it whose friction bound is sound for it: the certified-interval
block's ``_narrowest_holding`` in ``drake_cert.systems.certified_interval``.)
"""

from collections.abc import Sequence

from drake_cert.config import ConditionsTable
from drake_cert.errors import ConfigError
from drake_cert.synthesis.design import ControllerDesign


def preset_designs(designs: Sequence[ControllerDesign], conditions: ConditionsTable,
                   preset: str) -> list[ControllerDesign]:
    """The designs of every contiguous label range of ``preset`` (envelope included), in the
    order of :meth:`ConditionsTable.contiguous_ranges`. Raises ConfigError when the table lacks
    one (it was synthesized for other conditions)."""
    by_labels = {tuple(d.labels): d for d in designs if d.labels}
    chosen = []
    for labels in conditions.contiguous_ranges(preset):
        design = by_labels.get(tuple(labels))
        if design is None:
            raise ConfigError(f"the design table has no design for labels {list(labels)} of "
                              f"preset {preset!r}; synthesize it with these conditions")
        chosen.append(design)
    return chosen


def design_index_for_labels(designs: Sequence[ControllerDesign], labels: Sequence[str]) -> int:
    """Index of the design of exactly this label range."""
    wanted = tuple(labels)
    for i, d in enumerate(designs):
        if tuple(d.labels) == wanted:
            return i
    raise ConfigError(f"no design for labels {list(wanted)}")


def envelope_design_index(designs: Sequence[ControllerDesign], conditions: ConditionsTable,
                          preset: str) -> int:
    """Index of the design for the preset's whole family (its stiffness envelope)."""
    return design_index_for_labels(designs, conditions.preset(preset).labels)


def design_label_spans(designs: Sequence[ControllerDesign], conditions: ConditionsTable,
                       preset: str) -> list[tuple[int, int]]:
    """(first, last) place of each design's label range in the preset's friction order (the
    spans the combined decisions work on, ``drake_cert.systems.decision_combination``)."""
    return _label_spans(designs, list(conditions.preset(preset).labels))


def _label_spans(designs: Sequence[ControllerDesign], family: list[str]) -> list[tuple[int, int]]:
    """(first, last) place of each design's label range in the family's friction order."""
    places = [[family.index(label) for label in d.labels] for d in designs]
    return [(min(p), max(p)) for p in places]


def join_design_indices(designs: Sequence[ControllerDesign], conditions: ConditionsTable,
                        preset: str) -> dict[tuple[int, int], int]:
    """For every pair (i, j) of the preset's designs, the index of the design whose label range
    is the hull of both ranges in the preset's friction order: the narrowest design of the
    table that holds every stiffness either design holds (the join). ``designs`` as
    :func:`preset_designs` returns them."""
    family = list(conditions.preset(preset).labels)
    span = _label_spans(designs, family)
    join = {}
    for i, (a_lo, a_hi) in enumerate(span):
        for j, (b_lo, b_hi) in enumerate(span):
            hull = family[min(a_lo, b_lo):max(a_hi, b_hi) + 1]
            join[(i, j)] = design_index_for_labels(designs, hull)
    return join
