"""`python -m repnet serve` in a child process on free localhost ports, for benchmarks and hardening tests."""

from __future__ import annotations

import os
import random
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import IO

import httpx

ROOT = Path(__file__).resolve().parent.parent
PAGE_BYTES = os.sysconf("SC_PAGE_SIZE")


def _ephemeral_range() -> tuple[int, int]:
    try:
        with open("/proc/sys/net/ipv4/ip_local_port_range") as f:
            low, high = (int(v) for v in f.read().split())
        return low, high
    except (OSError, ValueError):
        return 32768, 60999  # Linux's default


def free_port(exclude: tuple[int, ...] = ()) -> int:
    """A port nothing is bound to, below the ephemeral range where possible: the child binds it
    seconds later (after loading the model), and in between any outgoing connection on the
    machine could take a port of the ephemeral range (bind(0) picks from it) as its source port."""
    low, _ = _ephemeral_range()
    rng = random.Random()
    for _ in range(50):
        port = rng.randrange(10000, low) if low > 11000 else 0
        with socket.socket() as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
            chosen = int(s.getsockname()[1])
        if chosen not in exclude:
            return chosen
    raise RuntimeError("no free localhost port found")


def process_tree(pid: int) -> list[int]:
    """`pid` and every process below it (a supervised service's workers; Linux /proc)."""
    children: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:  # the process ended meanwhile
            continue
        children.setdefault(int(fields[1]), []).append(int(entry.name))
    found, todo = [], [pid]
    while todo:
        current = todo.pop()
        found.append(current)
        todo += children.get(current, [])
    return found


def open_fds(pid: int) -> int:
    """The file descriptors `pid` and its workers hold open, summed (Linux /proc)."""
    total = 0
    for member in process_tree(pid):
        try:
            total += len(os.listdir(f"/proc/{member}/fd"))
        except OSError:  # the process ended meanwhile
            continue
    return total


def rss_bytes(pid: int) -> int:
    """Resident memory of process `pid` and its workers (Linux /proc)."""
    total = 0
    for member in process_tree(pid):
        try:
            with open(f"/proc/{member}/statm") as f:
                total += int(f.read().split()[1]) * PAGE_BYTES
        except OSError:
            continue
    return total


def _stat_cpu(stat: str) -> float:
    """User + system CPU seconds from the text of a /proc stat file (a process's or a thread's)."""
    fields = stat.rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def cpu_seconds(pid: int) -> float:
    """User + system CPU time used so far by process `pid` and its live workers (Linux /proc)."""
    total = 0.0
    for member in process_tree(pid):
        try:
            total += _stat_cpu(Path(f"/proc/{member}/stat").read_text())
        except OSError:
            continue
    return total


CpuTimes = dict[int, tuple[int, float]]  # thread id -> (its process, CPU seconds so far)


def thread_cpu_seconds(pid: int) -> CpuTimes:
    """CPU seconds so far of every thread of process `pid` and its workers (Linux /proc)."""
    found: CpuTimes = {}
    for member in process_tree(pid):
        try:
            tasks = list(Path(f"/proc/{member}/task").iterdir())
        except OSError:  # the process ended meanwhile
            continue
        for task in tasks:
            try:
                found[int(task.name)] = (member, _stat_cpu((task / "stat").read_text()))
            except OSError:
                continue
    return found


class ServiceProcess:
    """A `python -m repnet serve` child (or another module that takes its flags: `module`, e.g.
    "bench.ceiling") bound to 127.0.0.1 on
    free ports; a context manager."""

    def __init__(
        self,
        *flags: str,
        log: Path | None = None,
        env: dict[str, str] | None = None,
        module: str = "repnet serve",
    ) -> None:
        self.module = module
        self.http_port = free_port()
        self.grpc_port = free_port(exclude=(self.http_port,))
        self.flags = (
            "--host",
            "127.0.0.1",
            "--http-port",
            str(self.http_port),
            "--grpc-port",
            str(self.grpc_port),
            "--log-level",
            "warning",
            *flags,
        )
        self.log = log
        self.env = env or {}
        self.process: subprocess.Popen[bytes] | None = None
        self._log_file: IO[bytes] | None = None

    @property
    def url(self) -> str:
        """The HTTP base URL."""
        return f"http://127.0.0.1:{self.http_port}"

    @property
    def target(self) -> str:
        """The gRPC host:port."""
        return f"127.0.0.1:{self.grpc_port}"

    @property
    def pid(self) -> int:
        """The server process's id."""
        if self.process is None:
            raise RuntimeError("the service is not started")
        return self.process.pid

    def start(self, timeout: float = 90.0) -> ServiceProcess:
        """Start the child and wait until /readyz answers 200; RuntimeError if it exits first."""
        path = os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))
        env = {**os.environ, "PYTHONPATH": path, "ORT_DISABLE_TELEMETRY": "1", **self.env}
        self._log_file = self.log.open("wb") if self.log else None
        out = self._log_file if self._log_file else subprocess.DEVNULL
        self.process = subprocess.Popen(
            [sys.executable, "-m", *self.module.split(), *self.flags],
            cwd=ROOT,
            env=env,
            stdout=out,
            stderr=subprocess.STDOUT,
        )
        deadline = time.monotonic() + timeout
        while not self.ready():
            if self.process.poll() is not None:
                raise RuntimeError(f"the service exited with {self.process.returncode} before it was ready")
            if time.monotonic() > deadline:
                self.kill()
                raise RuntimeError(f"the service was not ready within {timeout:.0f} s")
            time.sleep(0.05)
        return self

    def ready(self) -> bool:
        """/readyz answers 200."""
        try:
            return httpx.get(f"{self.url}/readyz", timeout=1).status_code == 200
        except httpx.TransportError:
            return False

    def terminate(self, timeout: float = 30.0) -> int:
        """SIGTERM, then wait for the exit status (SIGKILL after `timeout`)."""
        if self.process is None:
            return 0
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
        try:
            return self.process.wait(timeout)
        except subprocess.TimeoutExpired:
            self.kill()
            raise
        finally:
            self._close_log()

    def kill(self) -> None:
        """Kill the server at once."""
        if self.process is not None and self.process.poll() is None:
            self.process.kill()
            self.process.wait()
        self._close_log()

    def _close_log(self) -> None:
        if self._log_file is not None:
            self._log_file.close()
            self._log_file = None

    def __enter__(self) -> ServiceProcess:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        try:
            self.terminate()
        finally:
            self.kill()
