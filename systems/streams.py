"""Independent random streams of the driving diagram (DESIGN 3: no noise stream is reused).

Every random draw of a drive comes from ``numpy.random.SeedSequence([seed, purpose, *keys])``
with a distinct ``purpose`` per use: the route's true stiffness per segment, the camera's
frame per tick, the attack per tick, the certificate and its selection draw per tick. Same
scenario seed, same draws; different purposes never share a stream.
"""

import numpy as np

from drake_cert.certification.seeds import seed_from_sequence

ROUTE = 1  # true stiffness of each segment (key: segment index)
CAMERA = 2  # the rendered (or chosen) frame of each tick (key: tick)
ATTACK = 3  # the attack's random start and noise draws at each tick (key: tick)
CERTIFICATE = 4  # the smoothing noise of each tick's certificate (key: tick)
CALIBRATION = 5  # the regression's conformal calibration before a drive (no key)
SELECTION = 6  # the selection samples of each tick's sequential decision (key: tick)


def stream_seed(seed: int, purpose: int, *keys: int) -> int:
    """A 63-bit integer seed for (seed, purpose, keys): for ``torch.Generator.manual_seed``."""
    return seed_from_sequence(np.random.SeedSequence([int(seed), int(purpose),
                                                      *(int(k) for k in keys)]))


def stream_rng(seed: int, purpose: int, *keys: int) -> np.random.Generator:
    """A numpy Generator on the stream (seed, purpose, keys)."""
    return np.random.default_rng(np.random.SeedSequence([int(seed), int(purpose),
                                                         *(int(k) for k in keys)]))
