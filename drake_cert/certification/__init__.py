"""Certification: statistics, the noisy sampler, smoothed classifier and regressor, run-time
stiffness intervals, attacks (DESIGN 3).

Imports only the foundation; never ``systems`` or ``synthesis``.
"""
