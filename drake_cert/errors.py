"""Typed errors. The CLI turns each into one line on stderr and exit code 2."""


class DrakeCertError(Exception):
    """Base class for every error a user can cause."""


class ConfigError(DrakeCertError, ValueError):
    """A configuration file or value is missing, unknown or non-physical."""


class DesignFormatError(DrakeCertError, ValueError):
    """A saved design file cannot be read (wrong schema, missing keys, bad values)."""


class InfeasibleDesign(DrakeCertError, RuntimeError):
    """A convex program or search found no design; the message names the failed condition."""


class CertificationError(DrakeCertError, ValueError):
    """Bad input to a certificate (shape, dtype, NaN, sigma, alpha, too few samples)."""


class ModelNotFoundError(DrakeCertError, FileNotFoundError):
    """A trained model file is missing; the message says which command makes it."""
