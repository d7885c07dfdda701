"""`drake-cert reproduce --executor ray --address HOST:PORT` against a real Ray cluster.

A head node is started on loopback with ``ray start --head`` (its own temp dir, free port, two
CPUs, and token authentication on with a token of its own, as a plain start has it on a
machine that holds ~/.ray/auth_token), a tiny reproduction runs on
it through the CLI and must write the serial executor's tables byte for byte; then that head,
and only it, is stopped by its own process handle (never ``ray stop``, which stops every Ray
on the machine). What the two fixes (worker niceness, token authentication) are for is
checked on that cluster: the client finds the token without RAY_AUTH_MODE (loopback, as
Ray's "auto" would), and the workers run at niceness 0 (Ray's default, 15, starved them on a
busy machine).
"""

import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from drake_cert.cli import main

# One frame of one preset, f and g at one sigma (6 cells), no calibration: the smallest run
# that goes through the executor.
TINY = ["reproduce", "--quick", "--presets", "rtk-like", "--frames", "1", "--sigmas", "0.25",
        "--no-regression", "--no-conformal", "--no-plots"]
AUTH_VARS = ("RAY_AUTH_MODE", "RAY_AUTH_TOKEN", "RAY_AUTH_TOKEN_PATH")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def ray_command() -> str:
    here = Path(sys.executable).with_name("ray")
    return str(here) if here.exists() else (shutil.which("ray") or "")


def processes_naming(text: str) -> list[int]:
    """Ids of live processes whose command line contains ``text`` (Linux /proc)."""
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                if text.encode() in (entry / "cmdline").read_bytes():
                    found.append(int(entry.name))
            except OSError:
                pass
    return found


class Head:
    """A ``ray start --head --block`` process of the test's own (session, temp dir, port)."""

    def __init__(self, root: Path, process: subprocess.Popen, port: int):
        self.root, self.process, self.port = root, process, port
        self.address, self.token = f"127.0.0.1:{port}", root / "token"

    def ready(self, timeout_s: float = 90.0) -> str:
        """The head's address, once it says it runs (it starts while the test computes)."""
        deadline = time.monotonic() + timeout_s
        while "Ray runtime started" not in (self.root / "head.log").read_text():
            assert self.process.poll() is None, (self.root / "head.log").read_text()[-2000:]
            assert time.monotonic() < deadline, f"the head did not start in {timeout_s} s"
            time.sleep(0.2)
        return self.address


@pytest.fixture(scope="module")
def loopback_head():
    """A Ray head on 127.0.0.1 that requires its own token (the module's tests share it),
    started in the background: :meth:`Head.ready` waits for it."""
    pytest.importorskip("ray", reason="Ray is the optional `ray` extra (`make test` installs it)")
    if not ray_command() or not Path("/proc").is_dir():
        pytest.skip("needs the `ray` command and /proc")
    # A short temp dir: Ray's unix sockets live under it (at most 107 bytes a path).
    root = Path(tempfile.mkdtemp(prefix="dc-ray-", dir="/tmp"))
    (root / "token").write_text(secrets.token_hex(32))
    env = {k: v for k, v in os.environ.items() if k not in AUTH_VARS}
    env.update(RAY_AUTH_MODE="token", RAY_AUTH_TOKEN_PATH=str(root / "token"))
    port = free_port()
    log = open(root / "head.log", "w")
    process = subprocess.Popen(
        [ray_command(), "start", "--head", "--block", "--port", str(port),
         "--node-ip-address", "127.0.0.1", "--num-cpus", "2", "--temp-dir", str(root / "t"),
         "--include-dashboard=false", "--disable-usage-stats",
         "--object-store-memory", str(100 * 2**20)],
        env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        yield Head(root, process, port)
    finally:
        process.send_signal(signal.SIGTERM)  # `ray start --block` stops its processes on SIGTERM
        try:
            process.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(process.pid, signal.SIGKILL)  # its own session: nobody else's processes
            process.wait()
        log.close()
        deadline = time.monotonic() + 15
        while processes_naming(str(root)) and time.monotonic() < deadline:
            time.sleep(0.2)
        left = processes_naming(str(root))
        shutil.rmtree(root, ignore_errors=True)
        assert not left, f"processes of the test's Ray head still alive: {left}"


@pytest.mark.slow  # ~55 s: a real Ray cluster
def test_a_real_loopback_cluster_gives_the_serial_tables_byte_for_byte(
        loopback_head, tmp_path, monkeypatch):
    from drake_cert.experiments.executors import RayExecutor

    assert main([*TINY, "--out", str(tmp_path / "serial")]) == 0  # while the head starts
    for var in AUTH_VARS:
        monkeypatch.delenv(var, raising=False)
    # The client's token, where Ray looks for one; RAY_AUTH_MODE stays unset, as in a shell.
    monkeypatch.setenv("RAY_AUTH_TOKEN_PATH", str(loopback_head.token))
    address = loopback_head.ready()

    executor = RayExecutor(workers=1, address=address)
    assert executor.auth_mode == "token"  # found, not asked for
    assert "RAY_AUTH_MODE" not in os.environ  # and the process's setting left as it was
    niceness = executor.map(lambda: (lambda task: os.nice(0)), [0])
    assert niceness == [0]  # Ray's default would be 15

    assert main([*TINY, "--out", str(tmp_path / "cluster"), "--executor", "ray",
                 "--workers", "1", "--address", address]) == 0
    for name in ("results.csv", "frames.csv", "tables.md"):
        assert (tmp_path / "cluster" / name).read_bytes() == \
            (tmp_path / "serial" / name).read_bytes(), name
    assert "RAY_AUTH_MODE" not in os.environ


def test_a_cluster_refusing_the_client_is_one_line_within_seconds(
        loopback_head, tmp_path, monkeypatch, capsys):
    address = loopback_head.ready()
    for var in AUTH_VARS:
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setenv("RAY_AUTH_MODE", "token")
    monkeypatch.setenv("RAY_AUTH_TOKEN", "not-the-cluster-token")
    start = time.perf_counter()
    assert main([*TINY, "--out", str(tmp_path), "--executor", "ray",
                 "--address", address]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "refuses this machine's Ray token" in err[0], err
    assert "ray get-auth-token" in err[0]
    assert time.perf_counter() - start < 15


def test_a_cluster_asking_for_a_token_this_machine_lacks_is_one_line(
        loopback_head, tmp_path, monkeypatch, capsys):
    address = loopback_head.ready()
    for var in AUTH_VARS:
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setenv("HOME", str(tmp_path))  # no ~/.ray/auth_token either
    assert main([*TINY, "--out", str(tmp_path / "out"), "--executor", "ray",
                 "--address", address]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "requires Ray token authentication" in err[0], err
    assert "RAY_AUTH_MODE=token" in err[0]


@pytest.mark.parametrize("address, loopback", [
    ("127.0.0.1:6379", True), ("127.3.2.1:1", True), ("localhost:6379", True),
    ("[::1]:6379", True), ("10.0.0.5:6379", False), ("head-node:6379", False),
    ("auto", False), ("ray://127.0.0.1:10001", False), (None, False),
])
def test_only_loopback_addresses_get_this_machines_token_unasked(address, loopback):
    from drake_cert.experiments.executors import is_loopback

    assert is_loopback(address) is loopback


def test_workers_run_at_niceness_0_unless_the_driver_names_another(monkeypatch):
    from drake_cert.experiments.executors import worker_env

    monkeypatch.delenv("RAY_worker_niceness", raising=False)
    assert worker_env()["RAY_worker_niceness"] == "0"
    monkeypatch.setenv("RAY_worker_niceness", "10")
    assert worker_env()["RAY_worker_niceness"] == "10"
