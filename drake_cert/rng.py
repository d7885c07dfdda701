"""torch generators whose whole state depends on every bit of a seed.

``torch.Generator().manual_seed(s)`` on CPU seeds mt19937 with ``init_genrand(s mod 2^32)``:
it keeps 32 of the bits of a seed, so the project's 63-bit stream seeds
(:mod:`drake_cert.certification.seeds`) that agree in their low 32 bits drew identical noise.
:func:`torch_generator` instead fills the whole mt19937 state (624 words) from
``numpy.random.SeedSequence(seed)`` and installs it with ``Generator.set_state``, after
checking once per process that this torch lays its CPU state out as written below (it raises
otherwise rather than fall back to 32-bit seeds). Other devices (CUDA's Philox) keep all 64
bits of ``manual_seed`` and use it. Same seed, same draws, on any machine with this torch.
"""

from __future__ import annotations

import functools
import struct
from typing import TYPE_CHECKING

import numpy as np

from drake_cert.errors import CertificationError

if TYPE_CHECKING:
    import torch

MT_WORDS = 624  # words of mt19937 state
# torch's CPU generator state (get_state/set_state): the legacy THGeneratorState, then the
# cached float normal. Little-endian, 5056 bytes in torch 2.x:
#   0 uint64 the_initial_seed | 8 int32 left | 12 int32 seeded | 16 uint64 next |
#   24 uint64 state[624] (one 32-bit word each) | 5016 double normal_x, normal_y, normal_rho |
#   5040 int32 normal_is_valid (+4 padding) | 5048 float next_float_normal_sample |
#   5052 bool its valid flag (+3 padding).
_CPU_STATE_BYTES = 5056
_CPU_HEADER = struct.Struct("<QiiQ")  # the_initial_seed, left, seeded, next
_CPU_WORDS_AT = _CPU_HEADER.size  # 24
_CPU_WORDS_END = _CPU_WORDS_AT + 8 * MT_WORDS  # 5016


def mt19937_words(seed: int) -> np.ndarray:
    """The 624 mt19937 state words :func:`torch_generator` installs for ``seed``:
    ``SeedSequence(seed).generate_state(624)``, a hash of every bit of the seed."""
    words = np.random.SeedSequence(_check_seed(seed)).generate_state(MT_WORDS, dtype=np.uint32)
    assert words.any(), "an all-zero mt19937 state never leaves zero"  # odds 2^-19968
    return words


def torch_generator(seed: int, device: torch.device | str | None = None
                    ) -> torch.Generator:
    """A ``torch.Generator`` on ``device`` (default CPU) whose state depends on every bit of
    ``seed`` (an integer in [0, 2^64)); same seed, same draws.

    On CPU the whole mt19937 state is :func:`mt19937_words` (``manual_seed`` would keep only
    32 bits); the first draw twists it, as after ``manual_seed``. ``initial_seed()`` is
    ``seed``. On other devices (Philox, 64-bit seeds) it is ``manual_seed(seed)``. Raises
    :class:`CertificationError` if this torch's CPU state layout is not the one checked for.
    """
    import torch

    seed = _check_seed(seed)
    device = torch.device("cpu" if device is None else device)
    if device.type != "cpu":
        return torch.Generator(device=device).manual_seed(seed)
    return _install_words(_cpu_state_template(), seed, mt19937_words(seed))


def _check_seed(seed) -> int:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise CertificationError(f"seed = {seed!r} must be a non-negative integer")
    seed = int(seed)
    if seed >= 1 << 64:
        raise CertificationError(f"seed = {seed} must be below 2**64")
    return seed


def _install_words(template: bytes, seed: int, words: np.ndarray) -> torch.Generator:
    """A CPU generator in ``template``'s state with ``words`` as its mt19937 state, about to
    twist (left 1, next 0), no cached normal, and ``seed`` as its initial seed."""
    import torch

    state = bytearray(template)
    _CPU_HEADER.pack_into(state, 0, seed, 1, 1, 0)
    state[_CPU_WORDS_AT:_CPU_WORDS_END] = words.astype("<u8").tobytes()
    state[_CPU_WORDS_END:] = bytes(len(state) - _CPU_WORDS_END)  # no cached normals
    generator = torch.Generator()
    generator.set_state(torch.frombuffer(state, dtype=torch.uint8).clone())
    return generator


def _init_genrand(seed: int) -> np.ndarray:
    """The reference mt19937 state after ``init_genrand(seed & 0xffffffff)`` (Matsumoto and
    Nishimura), which is what ``torch.Generator.manual_seed`` installs on CPU."""
    words = np.empty(MT_WORDS, dtype=np.uint32)
    words[0] = seed & 0xFFFFFFFF
    for j in range(1, MT_WORDS):
        prev = int(words[j - 1])
        words[j] = (1812433253 * (prev ^ (prev >> 30)) + j) & 0xFFFFFFFF
    return words


@functools.cache
def _cpu_state_template() -> bytes:
    """``get_state()`` of a freshly seeded CPU generator, once its layout is checked: the
    header and words of ``manual_seed`` sit where :data:`_CPU_HEADER` says, and installing
    those words through :func:`_install_words` reproduces its draws."""
    import torch

    probe = 0x5EED_0000_1234_ABCD  # above 2^32, to check the 64-bit seed field
    reference = torch.Generator().manual_seed(probe)
    state = reference.get_state().numpy().tobytes()
    expected = _init_genrand(probe)
    ok = (len(state) == _CPU_STATE_BYTES
          and _CPU_HEADER.unpack_from(state) == (probe, 1, 1, 0)
          and np.array_equal(np.frombuffer(state, "<u8", MT_WORDS, _CPU_WORDS_AT), expected)
          and not any(state[_CPU_WORDS_END:]))
    if ok:
        twin = _install_words(state, probe, expected)
        ok = (twin.get_state().numpy().tobytes() == state
              and torch.equal(torch.randn(8, generator=twin), torch.randn(8, generator=reference)))
    if not ok:
        raise CertificationError(
            f"torch {torch.__version__}'s CPU generator state is not the layout "
            f"drake_cert.rng was written for (checked on torch 2.13); "
            f"torch_generator cannot install full-width seeds, and manual_seed would keep only "
            f"32 bits of each stream's seed")
    return state
