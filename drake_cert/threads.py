"""torch's intra-op thread count, set for a block of work and given back afterwards.

The reproduction's executors and the driving Diagram compute on one thread, as each Ray worker
does, so that in-process and Ray runs do the same arithmetic. (The driving Diagram's ONNX
Runtime session has its own thread pool, one thread per available core: its outputs do not
depend on the thread count, DESIGN 3.8.) Run in the caller's own process
(the in-process executor, a notebook), that setting would otherwise outlive the call and leave
every later torch computation of the session on one thread.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager


def available_cores() -> int:
    """The CPU cores this process may run on (its affinity mask; ``os.cpu_count()`` where the
    platform has no affinity), at least 1."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


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
