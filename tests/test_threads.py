"""In-process work runs torch on one thread, as a Ray worker does, and gives the caller's
thread count back: a notebook that ran a reproduction or a drive keeps its own setting."""

import pytest
import torch

from drake_cert.experiments.executors import LocalExecutor
from drake_cert.threads import torch_threads


class OneThreadWorker:
    """Sets one thread itself on construction (any worker may): the map still gives the
    caller's count back."""

    def __init__(self):
        torch.set_num_threads(1)

    def __call__(self, task):
        return torch.get_num_threads()


@pytest.fixture
def three_threads():
    before = torch.get_num_threads()
    torch.set_num_threads(3)
    yield 3
    torch.set_num_threads(before)


def test_the_in_process_executor_gives_the_thread_count_back(three_threads):
    assert LocalExecutor().map(OneThreadWorker, ["a", "b"]) == [1, 1]
    assert torch.get_num_threads() == three_threads


def test_the_thread_count_comes_back_when_the_block_raises(three_threads):
    with pytest.raises(RuntimeError), torch_threads(1):
        assert torch.get_num_threads() == 1
        raise RuntimeError("a worker failed")
    assert torch.get_num_threads() == three_threads
