"""Convex gain synthesis, L1 norm, safe-speed search and independent verification."""
