"""drake-cert: certified robust perception-based lateral control (Yang et al., ACC 2023).

The public API, in the order a user meets it::

    import drake_cert as dc
    vehicle, conditions, settings = dc.load_vehicle(), dc.load_conditions(), dc.load_settings()
    design = dc.synthesize_design(vehicle, conditions.hull(("heavy_rain",)),
                                  conditions.condition("heavy_rain").friction_mu, settings)
    tape = dc.simulate(vehicle=vehicle, design=design, settings=settings,
                       stiffness_n_per_rad=45e3, friction_mu=0.5,
                       speed_mps=design.speed_mps, road=dc.Road.curve(radius_m=50.0))
    print(dc.metrics.peak_lateral_offset(tape), tape.lateral_offset_m[-1])

Packages: ``drake_cert`` (foundation: config, errors, io, dynamics, metrics; subpackages
``perception``, ``certification``, ``experiments``, ``cli``), ``synthesis`` (convex gain
synthesis, L1 norm, safe-speed search, verification), ``systems`` (Drake LeafSystems and
diagrams). Names below are resolved on first use (PEP 562), so ``import drake_cert`` imports
neither torch nor pydrake, and the foundation never imports the packages built on it.
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
    "InfeasibleDesign": "drake_cert.errors",
    "CertificationError": "drake_cert.errors",
    "metrics": "drake_cert.metrics",
    # synthesis
    "synthesize_design": "synthesis.table",
    "synthesize_table": "synthesis.table",
    "ControllerDesign": "synthesis.design",
    "load_design_file": "synthesis.design_io",
    "save_design_table": "synthesis.design_io",
    # systems
    "Road": "systems.road",
    "simulate": "systems.closed_loop",
    "Tape": "systems.closed_loop",
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
