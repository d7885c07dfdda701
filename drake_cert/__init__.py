"""drake-cert: certified robust perception-based lateral control (Yang et al., ACC 2023).

The public API, in the order a user meets it (the README's ten-line example runs it):
load the vehicle, conditions and settings; synthesize a design for a stiffness interval (or
the table); re-check a saved table independently (:func:`verify_design_table`, a
:class:`VerificationReport`); simulate the closed loop; read the tape with
:mod:`drake_cert.metrics`; load a scenario and drive it through the certified Diagram.

Packages, all under ``drake_cert``: the foundation (config, errors, io, dynamics, metrics),
``perception``, ``certification``, ``experiments``, ``cli``, and ``drake_cert.synthesis``
(convex gain synthesis, L1 norm, safe-speed search, verification) and ``drake_cert.systems``
(Drake LeafSystems and diagrams), whose sources sit in the repository's top-level folders
synthesis/ and systems/. Names below are resolved on first use (PEP 562), so
``import drake_cert`` imports neither torch nor pydrake, and the foundation never imports the
packages built on it.
"""

__version__ = "0.1.0"

_PUBLIC = {
    # foundation
    "load_vehicle": "drake_cert.config",
    "load_conditions": "drake_cert.config",
    "load_settings": "drake_cert.config",
    "VehicleParams": "drake_cert.config",
    "ConditionsTable": "drake_cert.config",
    "Settings": "drake_cert.config",
    "DrakeCertError": "drake_cert.errors",
    "ConfigError": "drake_cert.errors",
    "DesignFormatError": "drake_cert.errors",
    "InfeasibleDesign": "drake_cert.errors",
    "CertificationError": "drake_cert.errors",
    "metrics": "drake_cert.metrics",
    # synthesis
    "synthesize_design": "drake_cert.synthesis.table",
    "synthesize_label_range": "drake_cert.synthesis.table",
    "synthesize_table": "drake_cert.synthesis.table",
    "ControllerDesign": "drake_cert.synthesis.design",
    "load_design_file": "drake_cert.synthesis.design_io",
    "save_design_table": "drake_cert.synthesis.design_io",
    "verify_design_table": "drake_cert.synthesis.verify",
    "VerificationReport": "drake_cert.synthesis.verify",
    "common_lyapunov_certificate": "drake_cert.synthesis.switching",
    # systems
    "Road": "drake_cert.systems.road",
    "simulate": "drake_cert.systems.closed_loop",
    "Tape": "drake_cert.systems.closed_loop",
    "load_scenario": "drake_cert.systems.scenario",
    "build_certified_driving_diagram": "drake_cert.systems.driving",
    "drive": "drake_cert.systems.driving",
    "drive_scenario": "drake_cert.systems.driving",
    "with_overrides": "drake_cert.systems.driving",
}

__all__ = ["__version__", *_PUBLIC]


def __getattr__(name: str):
    if name not in _PUBLIC:
        raise AttributeError(f"module 'drake_cert' has no attribute {name!r}")
    import importlib

    where = _PUBLIC[name]
    module = importlib.import_module(where)
    value = module if where.endswith("." + name) else getattr(module, name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(__all__)
