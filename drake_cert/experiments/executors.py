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

import contextlib
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


# Ray (2.60) renices every worker process it starts by RAY_worker_niceness (default 15),
# read by the worker itself at start-up: on a machine with other work the workers then get
# only the CPU that is left (a loopback cluster on 2 busy cores finished 1 of 6 frames in
# 703 s). Ours run at 0 unless the driver's environment names another value.
WORKER_NICENESS = "RAY_worker_niceness"
AUTH_MODE = "RAY_AUTH_MODE"  # Ray's token authentication: "token" or "disabled"
TOKEN_HELP = ("put the cluster's token in RAY_AUTH_TOKEN or a file named by RAY_AUTH_TOKEN_PATH "
              "(`ray get-auth-token` on its head node prints it)")
REFUSED = ("the cluster refuses this machine's Ray token (RAY_AUTH_TOKEN, RAY_AUTH_TOKEN_PATH "
           "or ~/.ray/auth_token)")


def worker_env() -> dict[str, str]:
    """Environment variables of the Ray worker processes a map starts (its runtime_env)."""
    return {"OMP_NUM_THREADS": "1", "TOKENIZERS_PARALLELISM": "false",
            WORKER_NICENESS: os.environ.get(WORKER_NICENESS, "0")}


def is_loopback(address: str | None) -> bool:
    """Whether a "HOST:PORT" address names this machine by loopback (127.x, ::1, localhost)."""
    import ipaddress

    if not address or address == "auto" or address.startswith("ray://"):
        return False
    host = address.rpartition(":")[0].strip("[]")
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


@contextlib.contextmanager
def ray_auth_mode(mode: str | None):
    """RAY_AUTH_MODE = ``mode`` in this process while the block runs (None: as it is), and the
    value from before afterwards: Ray reads it into its process-wide config, and a local
    ``ray.init`` sets it to "token" for good, which would then reach a later cluster that
    does not authenticate (its actors are then never started)."""
    before = os.environ.get(AUTH_MODE)
    if mode is not None and mode != before:
        os.environ[AUTH_MODE] = mode
        _reload_ray_config()
    try:
        yield
    finally:
        if os.environ.get(AUTH_MODE) != before:
            if before is None:
                os.environ.pop(AUTH_MODE, None)
            else:
                os.environ[AUTH_MODE] = before
            _reload_ray_config()


def _reload_ray_config() -> None:
    from ray._raylet import AuthenticationTokenLoader, Config

    Config.initialize("")  # re-reads RAY_* from the environment (RAY_AUTH_MODE among them)
    AuthenticationTokenLoader.instance().reset_cache()


@contextlib.contextmanager
def _quiet_stderr():
    """File descriptor 2 to /dev/null: Ray's C++ client logs each failed try there; the caller
    reports the outcome in one line of its own."""
    import sys

    sys.stderr.flush()
    try:
        saved = os.dup(2)
    except OSError:  # no file descriptor 2: nothing to quiet
        yield
        return
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def _gcs_refusal(address: str, timeout_s: float) -> str | None:
    """None when the cluster's GCS at "HOST:PORT" takes this process's credentials, "auth" when
    it refuses them, else the error (one try, ``timeout_s``; about a second when it answers)."""
    from ray._raylet import InnerGcsClient
    from ray.exceptions import AuthenticationError

    with _quiet_stderr():
        try:
            InnerGcsClient.standalone(address, None, int(timeout_s * 1000))
        except AuthenticationError:
            return "auth"
        except Exception as e:  # any other refusal, reported in one line
            return str(e).splitlines()[0] if str(e) else type(e).__name__
    return None


def cluster_auth_mode(address: str | None, timeout_s: float = 10.0) -> str | None:
    """The RAY_AUTH_MODE this process connects to the cluster at ``address`` with: None (as
    it is) or "token"; raises :class:`ConfigError` in one line, within seconds, when the
    cluster does not take it (Ray alone retries, 20 s to 2 min, then fails with a traceback).

    A cluster started with plain ``ray start --head`` on a machine that holds a Ray token
    (``~/.ray/auth_token``, written by any local ``ray.init()``) requires that token, and Ray
    sends it only to an address it found itself ("auto"), never to one given. A loopback
    address is this machine: where RAY_AUTH_MODE is unset, the cluster refuses us and a token
    is at hand (RAY_AUTH_TOKEN, RAY_AUTH_TOKEN_PATH or ~/.ray/auth_token), it is sent as
    "auto" would. Other addresses need the user's RAY_AUTH_MODE=token and token. "auto", None
    and "ray://" (Ray Client) addresses are left to Ray."""
    if address is None or address == "auto" or address.startswith("ray://"):
        return None
    try:
        from ray._raylet import AuthenticationTokenLoader, Config, InnerGcsClient  # noqa: F401
    except ImportError:  # no Ray (or one without these: another version): left to ray.init
        return None
    with ray_auth_mode(None):  # whatever a probe changes, this process's setting comes back
        refusal = _gcs_refusal(address, timeout_s)
        if refusal is None:
            return None
        if refusal != "auth":
            raise ConfigError(f"--address {address}: no Ray cluster answers there ({refusal})")
        mode = os.environ.get(AUTH_MODE, "").lower()
        loader = AuthenticationTokenLoader.instance()
        loader.reset_cache()  # the token sources as they are now, not as first read
        has_token = loader.has_token(ignore_auth_mode=True)
        if mode == "token":
            raise ConfigError(f"--address {address}: {REFUSED}; {TOKEN_HELP}")
        if not (mode == "" and has_token and is_loopback(address)):
            raise ConfigError(f"--address {address}: the cluster requires Ray token "
                              f"authentication; set RAY_AUTH_MODE=token and {TOKEN_HELP}")
        with ray_auth_mode("token"):
            refusal = _gcs_refusal(address, timeout_s)
    if refusal == "auth":
        raise ConfigError(f"--address {address}: {REFUSED}; {TOKEN_HELP}")
    if refusal is not None:
        raise ConfigError(f"--address {address}: no Ray cluster answers there ({refusal})")
    return "token"


class RayExecutor:
    """Runs tasks on ``workers`` Ray actors (each builds its worker once).

    ``address``: an existing cluster ("HOST:PORT" of its head's GCS, "auto" or
    "ray://host:port"); None starts a local Ray with ``workers`` CPUs on demand. Results come
    back in task order. The workers run at niceness 0 (:func:`worker_env`); a cluster's token
    authentication is settled here, before any work (:func:`cluster_auth_mode`).
    """

    def __init__(self, workers: int = 2, address: str | None = None,
                 gpus_per_worker: float = 0.0):
        if workers < 1:
            raise ConfigError(f"workers = {workers} must be >= 1")
        if not 0.0 <= gpus_per_worker <= 1.0:
            raise ConfigError(f"gpus_per_worker = {gpus_per_worker} must be in [0, 1]")
        check_cluster_address(address)
        self.workers, self.address = int(workers), address
        # each worker's share of a GPU (Ray's num_gpus): its certificates sample on it, its
        # episodes run on its CPU
        self.gpus_per_worker = float(gpus_per_worker)
        self.auth_mode = cluster_auth_mode(address)

    def map(self, make_worker, tasks, progress=None, on_result=None, stop=None):
        if not tasks:
            return []
        try:
            import ray
        except ImportError:
            raise ConfigError("--executor ray needs Ray: pip install 'drake-cert[ray]'") from None
        started_here = not ray.is_initialized()
        with contextlib.ExitStack() as session:
            if started_here:
                self._init(ray, session)
            return self._map(ray, make_worker, tasks, progress, on_result, stop)

    def _init(self, ray, session: contextlib.ExitStack) -> None:
        """``ray.init`` for this map; ``session`` undoes it (and its RAY_AUTH_MODE) at the end."""
        env = worker_env()
        kwargs = dict(address=self.address, runtime_env={"env_vars": env}, log_to_driver=False,
                      include_dashboard=False, configure_logging=False)
        if self.address is None:
            kwargs["num_cpus"] = self.workers
        if self.address is None or is_loopback(self.address):
            # This machine's workers import the driver's working tree.
            env["PYTHONPATH"] = os.pathsep.join(
                p for p in (_project_root(), os.environ.get("PYTHONPATH", "")) if p)
        session.enter_context(ray_auth_mode(self.auth_mode))
        try:
            ray.init(**kwargs)
        except ConnectionError as e:  # "auto" with no Ray running on this machine
            raise ConfigError(f"--address {self.address}: {e}") from None
        session.callback(ray.shutdown)

    def _map(self, ray, make_worker, tasks, progress, on_result, stop) -> list[Any]:
        actor_class = ray.remote(num_cpus=1, num_gpus=self.gpus_per_worker)(_Actor)
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


class _Actor:
    def __init__(self, make_worker):
        import torch

        from drake_cert.certification.sampler import retain_freed_memory

        torch.set_num_threads(1)
        retain_freed_memory()  # a worker process that only samples: keep freed memory
        self._worker = make_worker()

    def run(self, task):
        return self._worker(task)


class CpuTimed:
    """A worker that returns ``(result, cpu_s)``: its wrapped worker's result and the CPU
    seconds of the process that ran it (one thread per worker: the work's own CPU time)."""

    def __init__(self, worker):
        self._worker = worker

    def __call__(self, task):
        import time

        start = time.process_time()
        result = self._worker(task)
        return result, time.process_time() - start


def cpu_timed(make_worker):
    """``make_worker`` whose workers are :class:`CpuTimed`."""
    return lambda: CpuTimed(make_worker())


def _project_root() -> str:
    return os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def make_executor(name: str, workers: int = 2, address: str | None = None,
                  gpus_per_worker: float = 0.0) -> Executor:
    """``local`` (default) or ``ray`` (``gpus_per_worker``: each Ray worker's share of a GPU,
    for work that samples on CUDA)."""
    if name == "local":
        return LocalExecutor()
    if name == "ray":
        return RayExecutor(workers, address, gpus_per_worker)
    raise ConfigError(f"executor {name!r} is not one of {', '.join(EXECUTORS)}")
