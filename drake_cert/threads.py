"""torch's intra-op thread count, set for a block of work and given back afterwards.

The reproduction's executors and the driving Diagram compute on one thread, as each Ray worker
does, so that in-process and Ray runs do the same arithmetic. Run in the caller's own process
(the in-process executor, a notebook), that setting would otherwise outlive the call and leave
every later torch computation of the session on one thread.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager


@contextmanager
def torch_threads(threads: int) -> Iterator[None]:
    """Run the block with ``torch.set_num_threads(threads)``; the caller's count is restored
    on exit (also when the block raises)."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(before)
