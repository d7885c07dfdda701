"""drake-cert: certified robust perception-based lateral control (Yang et al., ACC 2023).

Packages: ``drake_cert`` (configuration, perception, certification, CLI),
``systems`` (Drake LeafSystems and diagrams), ``synthesis`` (convex gain synthesis,
L1 norm, safe-speed search, verification).
"""

__version__ = "0.1.0"
