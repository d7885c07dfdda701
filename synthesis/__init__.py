"""Convex gain synthesis, L1 norm, safe-speed search and independent verification."""

from drake_cert.synthesis.l1_norm import l1_norm

__all__ = ["l1_norm"]
