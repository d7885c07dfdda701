"""Experiments: perception evaluation and the reproduction of the paper's tables.

Like ``drake_cert.cli``, may import from every package; nothing imports it.
"""
