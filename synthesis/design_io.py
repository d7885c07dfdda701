"""Saving and loading designs as YAML (DESIGN 5.4): schema version, provenance, one idea.

A design table file (``drake-cert synthesize --out``)::

    schema_version: 3
    provenance: {schema_version, command, git_revision, seed, created_utc}
    vehicle: {...}        # VehicleParams used
    settings: {...}       # Settings used (controller and synthesis)
    conditions: {...}     # ConditionsTable used (optional)
    designs: [ {labels, stiffness_lo_n_per_rad, ..., k_m: [4 numbers], ..., margins: {...}} ]
    switching: [ {family, method, designs_covered, decay_rate_per_s, dwell_time_s, ...} ]
                          # optional: drake_cert.synthesis.switching certificates, one per preset

The ``switching`` section is table-level and optional (files written before it load; verify
then notes its absence). It is not part of any design, so the reproduction's run identity,
which hashes the designs only, does not depend on it.

A single-design file has ``design: {...}`` instead of ``designs``. Loading checks every key
and value (a design's ``margins`` keys are :data:`drake_cert.synthesis.design.MARGIN_KEYS`) and
raises
:class:`DesignFormatError` naming the file and the offending key. Files are written
atomically.

Schema versions: 2 added ``tire_slip_bound`` and ``certified_law`` (version 1 files, certified
with an older grip rule, are refused); 3 renamed the margin ``steady_state_offset_m`` to
``steady_state_lane_margin_m`` (it always held the lane margin left at the steady state, not
an offset). A version 2 file is read with that one key renamed, which changes nothing else.
"""

import dataclasses
import math
from pathlib import Path

import yaml

from drake_cert.config import (
    ConditionsTable,
    Settings,
    VehicleParams,
    load_typed_mapping,
    parse_yaml,
    read_yaml_text,
)
from drake_cert.errors import ConfigError, DesignFormatError
from drake_cert.io import atomic_write_text
from drake_cert.synthesis.design import MARGIN_KEYS, ControllerDesign
from drake_cert.synthesis.switching import (
    SwitchingCertificate,
    certificate_from_dict,
    certificate_to_dict,
)

DESIGN_SCHEMA_VERSION = 3  # 2: tire_slip_bound, certified_law; Fiala grip rule.
# 3: margin steady_state_offset_m renamed steady_state_lane_margin_m
# older schema versions still read: version -> {old margin key: new margin key}
RENAMED_MARGINS = {2: {"steady_state_offset_m": "steady_state_lane_margin_m"}}
TOP_KEYS_REQUIRED = ("schema_version", "provenance", "vehicle", "settings")
TOP_KEYS_OPTIONAL = ("conditions", "designs", "design", "switching")


@dataclasses.dataclass
class DesignTable:
    """Designs with the vehicle, settings (and conditions) they were synthesized for."""

    designs: list[ControllerDesign]
    vehicle: VehicleParams
    settings: Settings
    provenance: dict
    conditions: ConditionsTable | None = None
    # switching certificates (drake_cert.synthesis.switching), one per family; None: not computed
    switching: tuple[SwitchingCertificate, ...] | None = None


def design_to_dict(design: ControllerDesign) -> dict:
    """Plain YAML-able mapping of one design (floats, lists; ``k_m`` under ``k_m``)."""
    return {
        "labels": list(design.labels),
        "stiffness_lo_n_per_rad": float(design.stiffness_lo_n_per_rad),
        "stiffness_hi_n_per_rad": float(design.stiffness_hi_n_per_rad),
        "nominal_stiffness_n_per_rad": float(design.nominal_stiffness_n_per_rad),
        "friction_mu_lo": float(design.friction_mu_lo),
        "k_m": [float(x) for x in design.k_m],
        "gain_speed_max_mps": float(design.gain_speed_max_mps),
        "filter_gain": float(design.filter_gain),
        "speed_mps": float(design.speed_mps),
        "failed_condition": str(design.failed_condition),
        "margins": {str(k): float(v) for k, v in design.margins.items()},
        "tire_slip_bound": float(design.tire_slip_bound),
        "certified_law": str(design.certified_law),
        "speed_limited_by": str(design.speed_limited_by),
    }


def dump_design_table(table: DesignTable, single: bool = False) -> str:
    """YAML text of the table (``single``: a one-design file with top-level ``design``)."""
    data = {
        "schema_version": DESIGN_SCHEMA_VERSION,
        "provenance": dict(table.provenance),
        "vehicle": dataclasses.asdict(table.vehicle),
        "settings": dataclasses.asdict(table.settings),
    }
    if table.conditions is not None:
        data["conditions"] = dataclasses.asdict(table.conditions)
    if single:
        if len(table.designs) != 1:
            raise ValueError("a single-design file needs exactly one design")
        data["design"] = design_to_dict(table.designs[0])
    else:
        data["designs"] = [design_to_dict(d) for d in table.designs]
        if table.switching is not None:
            data["switching"] = [certificate_to_dict(c) for c in table.switching]
    return yaml.safe_dump(data, sort_keys=False, default_flow_style=None, width=100)


def with_switching_certificates(table: DesignTable) -> DesignTable:
    """The table with its ``switching`` section computed from its own vehicle, settings,
    designs and conditions (:func:`drake_cert.synthesis.switching.table_switching_certificates`: one
    certificate per preset, or one for all designs without conditions; a few seconds)."""
    from drake_cert.synthesis.switching import table_switching_certificates

    certificates = table_switching_certificates(table.vehicle, table.designs, table.settings,
                                                table.conditions)
    return dataclasses.replace(table, switching=certificates)


def save_design_table(path: str | Path, table: DesignTable, single: bool = False,
                      switching: str | bool = "auto") -> Path:
    """Write the table (or its single design) to ``path`` atomically.

    ``switching``: whether to compute the switching certificates of a table that has none
    (:func:`with_switching_certificates`) before writing: ``"auto"`` (the default) when the
    table embeds its conditions, as ``drake-cert synthesize`` writes it; True always; False
    never. A table that already holds certificates is written as it is (a changed design
    list with old certificates fails verify), and a single-design file holds none.
    """
    if switching not in ("auto", True, False):
        raise ValueError(f"switching = {switching!r} must be 'auto', True or False")
    if (not single and table.switching is None
            and (switching is True or (switching == "auto" and table.conditions is not None))):
        table = with_switching_certificates(table)
    return atomic_write_text(path, dump_design_table(table, single))


def load_design_file(path: str | Path) -> DesignTable:
    """Read a design table or single-design file; :class:`DesignFormatError` if unreadable."""
    where = str(path)
    text = read_yaml_text(path, DesignFormatError)
    return parse_design_table(parse_yaml(text, where, DesignFormatError), where)


def parse_design_table(raw, where: str) -> DesignTable:
    """Validate an already-parsed design file (see module docstring)."""
    if not isinstance(raw, dict):
        raise DesignFormatError(f"{where}: top level must be a mapping, got {type(raw).__name__}")
    unknown = sorted(set(raw) - set(TOP_KEYS_REQUIRED) - set(TOP_KEYS_OPTIONAL))
    if unknown:
        raise DesignFormatError(f"{where}: unknown top-level key {unknown[0]!r}")
    for key in TOP_KEYS_REQUIRED:
        if key not in raw:
            raise DesignFormatError(f"{where}: missing top-level key {key!r}")
    readable = " and ".join(str(v) for v in sorted({*RENAMED_MARGINS, DESIGN_SCHEMA_VERSION}))
    if raw["schema_version"] == 1:
        raise DesignFormatError(
            f"{where}: schema_version = 1: a design table certified with the old slip-angle "
            f"grip rule and the gradient law's conditions; this version reads {readable} "
            "(re-run drake-cert synthesize --out)")
    if raw["schema_version"] not in (DESIGN_SCHEMA_VERSION, *RENAMED_MARGINS):
        raise DesignFormatError(f"{where}: schema_version = {raw['schema_version']!r}; this "
                                f"version reads {readable}")
    if not isinstance(raw["provenance"], dict):
        raise DesignFormatError(f"{where}: provenance must be a mapping")
    if ("designs" in raw) == ("design" in raw):
        raise DesignFormatError(f"{where}: expected exactly one of 'designs' (a table) or "
                                "'design' (one design)")
    try:
        vehicle = load_typed_mapping(VehicleParams, raw["vehicle"], f"{where}: vehicle")
        settings = load_typed_mapping(Settings, raw["settings"], f"{where}: settings")
        conditions = (load_typed_mapping(ConditionsTable, raw["conditions"],
                                         f"{where}: conditions")
                      if "conditions" in raw else None)
    except ConfigError as e:
        raise DesignFormatError(str(e)) from None
    if "design" in raw:
        entries, key = [raw["design"]], "design"
    else:
        entries, key = raw["designs"], "designs"
        if not isinstance(entries, list) or not entries:
            raise DesignFormatError(f"{where}: designs must be a non-empty list")
    renamed = RENAMED_MARGINS.get(raw["schema_version"], {})
    designs = [design_from_dict(_with_margins_renamed(e, renamed),
                                f"{where}: {key}" + ("" if key == "design" else f"[{i}]"))
               for i, e in enumerate(entries)]
    switching = None
    if "switching" in raw:
        if "design" in raw:
            raise DesignFormatError(f"{where}: a single-design file holds no switching section")
        if not isinstance(raw["switching"], list):
            raise DesignFormatError(f"{where}: switching must be a list of certificates")
        try:
            switching = tuple(certificate_from_dict(c, f"{where}: switching[{i}]")
                              for i, c in enumerate(raw["switching"]))
        except ValueError as e:
            raise DesignFormatError(str(e)) from None
    return DesignTable(designs, vehicle, settings, dict(raw["provenance"]), conditions,
                       switching)


def _with_margins_renamed(entry, renamed: dict):
    """A design mapping of an older schema with its margin keys renamed (``renamed``: old ->
    new); anything that is not a design mapping with a margins mapping is left as it is."""
    if not renamed or not isinstance(entry, dict) or not isinstance(entry.get("margins"), dict):
        return entry
    margins = {renamed.get(k, k): v for k, v in entry["margins"].items()}
    return {**entry, "margins": margins}


_FLOAT_FIELDS = ("stiffness_lo_n_per_rad", "stiffness_hi_n_per_rad",
                 "nominal_stiffness_n_per_rad", "friction_mu_lo", "gain_speed_max_mps",
                 "filter_gain", "speed_mps", "tire_slip_bound")
CERTIFIABLE_LAWS = ("piecewise_constant", "gradient")


# design keys a file may leave out (written before they existed): their defaults apply
OPTIONAL_DESIGN_KEYS = ("speed_limited_by",)


def design_from_dict(data, where: str) -> ControllerDesign:
    """One design mapping -> :class:`ControllerDesign`; raises :class:`DesignFormatError`."""
    if not isinstance(data, dict):
        raise DesignFormatError(f"{where} must be a mapping")
    fields = [f.name for f in dataclasses.fields(ControllerDesign)]
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise DesignFormatError(f"{where}: unknown key {unknown[0]!r}")
    missing = [f for f in fields if f not in data and f not in OPTIONAL_DESIGN_KEYS]
    if missing:
        raise DesignFormatError(f"{where}: missing key {missing[0]!r}")
    for key in _FLOAT_FIELDS:
        _require_number(data[key], f"{where}.{key}")
    labels = data["labels"]
    if not isinstance(labels, list) or not all(isinstance(x, str) for x in labels):
        raise DesignFormatError(f"{where}.labels must be a list of label names")
    k_m = data["k_m"]
    if not isinstance(k_m, list) or len(k_m) != 4:
        raise DesignFormatError(f"{where}.k_m must be a list of 4 numbers, got {k_m!r}")
    for i, x in enumerate(k_m):
        _require_number(x, f"{where}.k_m[{i}]")
    for key in ("failed_condition", "speed_limited_by"):
        if not isinstance(data.get(key, ""), str):
            raise DesignFormatError(f"{where}.{key} must be a string")
    margins = data["margins"]
    if not isinstance(margins, dict):
        raise DesignFormatError(f"{where}.margins must be a mapping")
    for k, v in margins.items():
        if k not in MARGIN_KEYS:
            old = next((f" (schema {DESIGN_SCHEMA_VERSION} calls it {new!r})"
                        for names in RENAMED_MARGINS.values() for o, new in names.items()
                        if o == k), "")
            raise DesignFormatError(f"{where}.margins: unknown key {k!r}{old}; known: "
                                    f"{', '.join(MARGIN_KEYS)}")
        _require_number(v, f"{where}.margins.{k}", allow_inf=True)
    lo, hi = data["stiffness_lo_n_per_rad"], data["stiffness_hi_n_per_rad"]
    if not 0.0 < lo < hi:
        raise DesignFormatError(f"{where}: stiffness interval [{lo}, {hi}] N/rad must satisfy "
                                "0 < lo < hi")
    if data["certified_law"] not in CERTIFIABLE_LAWS:
        raise DesignFormatError(f"{where}.certified_law = {data['certified_law']!r} must be one "
                                f"of {', '.join(CERTIFIABLE_LAWS)}")
    if not 0.0 <= data["tire_slip_bound"] < 1.0:
        raise DesignFormatError(f"{where}.tire_slip_bound = {data['tire_slip_bound']} must lie "
                                "in [0, 1)")
    for key in ("speed_mps", "filter_gain", "gain_speed_max_mps", "friction_mu_lo"):
        if data[key] < 0.0:
            raise DesignFormatError(f"{where}.{key} = {data[key]} must not be negative")
    return ControllerDesign(
        labels=list(labels),
        stiffness_lo_n_per_rad=float(lo),
        stiffness_hi_n_per_rad=float(hi),
        nominal_stiffness_n_per_rad=float(data["nominal_stiffness_n_per_rad"]),
        friction_mu_lo=float(data["friction_mu_lo"]),
        k_m=[float(x) for x in k_m],
        gain_speed_max_mps=float(data["gain_speed_max_mps"]),
        filter_gain=float(data["filter_gain"]),
        speed_mps=float(data["speed_mps"]),
        failed_condition=data["failed_condition"],
        margins={str(k): float(v) for k, v in margins.items()},
        tire_slip_bound=float(data["tire_slip_bound"]),
        certified_law=data["certified_law"],
        speed_limited_by=data.get("speed_limited_by", ""),
    )


def _require_number(value, key: str, allow_inf: bool = False) -> None:
    ok = isinstance(value, (int, float)) and not isinstance(value, bool)
    if ok and not allow_inf:
        ok = math.isfinite(value)
    if not ok or (isinstance(value, float) and math.isnan(value)):
        raise DesignFormatError(f"{key} = {value!r} must be a finite number")
