"""Perception: procedural driving frames, data sets and loaders, models, training (DESIGN 3).

Imports only the foundation (``drake_cert.config``, ``errors``, ``io``); never ``systems`` or
``synthesis``.
"""
