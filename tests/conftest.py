"""Shared pytest fixtures (add fixtures additively; keep each one cheap or session-scoped)."""

import pytest


@pytest.fixture(scope="session")
def default_design_table():
    """The design table synthesized once for the shipped vehicle, conditions and settings.

    A ``drake_cert.synthesis.design_io.DesignTable`` (designs in
    ``drake_cert.synthesis.table.design_label_ranges`` order); takes a few seconds, shared by the
    synthesis and verify tests.
    """
    from drake_cert.config import load_conditions, load_settings, load_vehicle
    from drake_cert.io import provenance
    from drake_cert.synthesis.design_io import DesignTable
    from drake_cert.synthesis.table import synthesize_table

    vehicle, conditions, settings = load_vehicle(), load_conditions(), load_settings()
    designs = synthesize_table(vehicle, conditions, settings)
    return DesignTable(designs, vehicle, settings,
                       provenance(seed=None, command=["pytest", "default_design_table"]),
                       conditions)


@pytest.fixture(scope="session")
def certified_design_table(default_design_table):
    """:func:`default_design_table` with its switching certificates (what
    ``drake-cert synthesize --out`` writes); computed once per session (several seconds)."""
    from drake_cert.synthesis.design_io import with_switching_certificates

    return with_switching_certificates(default_design_table)


@pytest.fixture(scope="session", autouse=True)
def one_torch_thread():
    """Tiny torch models run on one thread: no oversubscription on a shared 2-core machine."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="session", autouse=True)
def calibration_cache_in_a_temporary_folder(tmp_path_factory):
    """Calibrations the tests compute are cached in a folder of this session, not the user's."""
    import os

    from drake_cert.certification.calibration_cache import CACHE_ENV

    before = os.environ.get(CACHE_ENV)
    os.environ[CACHE_ENV] = str(tmp_path_factory.mktemp("calibration_cache"))
    yield
    if before is None:
        os.environ.pop(CACHE_ENV, None)
    else:
        os.environ[CACHE_ENV] = before
