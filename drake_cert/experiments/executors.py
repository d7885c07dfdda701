"""Executors for sweeps: in-process by default, Ray for users who outgrow one machine.

An executor maps a worker over tasks and returns the results in task order. The worker is
built once per process (``make_worker()``; it loads models and designs once) and called as
``worker(task)``; the executor runs workers on one torch thread each (workers do not set it).
Results never depend on the executor or the number of workers: every task
carries its own seeds, and the worker holds no state that changes its answers (caches only).
``on_result(index, result)`` sees each result as it arrives (in the driver: a caller stores
it, so an interrupted run keeps what it finished); once ``stop()`` returns True no new task
starts, and the tasks never started come back as None.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from typing import Any, Protocol

from drake_cert.errors import ConfigError

EXECUTORS = ("local", "ray")


class Executor(Protocol):
    def map(self, make_worker: Callable[[], Callable[[Any], Any]], tasks: Sequence[Any],
            progress: Callable[[int], None] | None = None,
            on_result: Callable[[int, Any], None] | None = None,
            stop: Callable[[], bool] | None = None) -> list[Any]:
        """Results of ``worker(task)`` for every task, in task order; ``progress(1)`` per task."""


def _report(index, result, progress, on_result) -> None:
    if on_result is not None:
        on_result(index, result)
    if progress is not None:
        progress(1)


class LocalExecutor:
    """Runs every task in this process, one after another."""

    def map(self, make_worker, tasks, progress=None, on_result=None, stop=None):
        from drake_cert.threads import torch_threads

        results: list[Any] = [None] * len(tasks)
        if not tasks:
            return results
        # One torch thread, as in a Ray actor (the same arithmetic whatever the executor);
        # this process gets its own count back when the map ends.
        with torch_threads(1):
            worker = make_worker()
            for index, task in enumerate(tasks):
                if stop is not None and stop():
                    break
                results[index] = worker(task)
                _report(index, results[index], progress, on_result)
        return results


def check_cluster_address(address: str | None, timeout_s: float = 5.0) -> None:
    """Raise :class:`ConfigError` unless ``address`` ("HOST:PORT" or "ray://HOST:PORT") takes a
    TCP connection within ``timeout_s``: Ray itself retries an unreachable address for minutes
    without a word. None (a local Ray started here) and "auto" (one already running on this
    machine, which Ray finds or refuses at once) are left to Ray."""
    import socket

    if address is None or address == "auto":
        return
    host, sep, port = address.removeprefix("ray://").rpartition(":")
    if not sep or not host or not port.isdigit():
        raise ConfigError(f"--address {address!r}: expected 'auto', 'HOST:PORT' or "
                          "'ray://HOST:PORT'")
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s):
            pass
    except OSError as e:
        raise ConfigError(f"--address {address}: no Ray cluster answers at {host}:{port} "
                          f"({e.strerror or e})") from None


class RayExecutor:
    """Runs tasks on ``workers`` Ray actors (each builds its worker once).

    ``address``: an existing cluster ("auto" or "ray://host:port"); None starts a local Ray
    with ``workers`` CPUs on demand. Results come back in task order.
    """

    def __init__(self, workers: int = 2, address: str | None = None):
        if workers < 1:
            raise ConfigError(f"workers = {workers} must be >= 1")
        check_cluster_address(address)
        self.workers, self.address = int(workers), address

    def map(self, make_worker, tasks, progress=None, on_result=None, stop=None):
        if not tasks:
            return []
        try:
            import ray
        except ImportError:
            raise ConfigError("--executor ray needs Ray: pip install 'drake-cert[ray]'") from None
        started_here = not ray.is_initialized()
        if started_here:
            env = {"env_vars": {"OMP_NUM_THREADS": "1", "TOKENIZERS_PARALLELISM": "false"}}
            kwargs = dict(address=self.address, runtime_env=env, log_to_driver=False,
                          include_dashboard=False, configure_logging=False)
            if self.address is None:
                kwargs["num_cpus"] = self.workers
                # The working tree's packages must be importable by the workers.
                kwargs["runtime_env"]["env_vars"]["PYTHONPATH"] = os.pathsep.join(
                    p for p in (_project_root(), os.environ.get("PYTHONPATH", "")) if p)
            try:
                ray.init(**kwargs)
            except ConnectionError as e:  # "auto" with no Ray running on this machine
                raise ConfigError(f"--address {self.address}: {e}") from None
        try:
            actor_class = ray.remote(num_cpus=1)(_Actor)
            actors = [actor_class.remote(make_worker) for _ in range(self.workers)]
            pending = {}
            results: list[Any] = [None] * len(tasks)
            next_task = 0

            def submit(actor) -> None:
                nonlocal next_task
                if next_task < len(tasks) and not (stop is not None and stop()):
                    pending[actor.run.remote(tasks[next_task])] = (next_task, actor)
                    next_task += 1

            for actor in actors:  # one task in flight per actor
                submit(actor)
            while pending:
                done, _ = ray.wait(list(pending), num_returns=1)
                index, actor = pending.pop(done[0])
                results[index] = ray.get(done[0])
                _report(index, results[index], progress, on_result)
                submit(actor)
            return results
        finally:
            if started_here:
                ray.shutdown()


class _Actor:
    def __init__(self, make_worker):
        import torch

        torch.set_num_threads(1)
        self._worker = make_worker()

    def run(self, task):
        return self._worker(task)


def _project_root() -> str:
    return os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def make_executor(name: str, workers: int = 2, address: str | None = None) -> Executor:
    """``local`` (default) or ``ray``."""
    if name == "local":
        return LocalExecutor()
    if name == "ray":
        return RayExecutor(workers, address)
    raise ConfigError(f"executor {name!r} is not one of {', '.join(EXECUTORS)}")
