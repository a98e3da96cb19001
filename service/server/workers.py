"""Workers: `repnet serve --workers N` as N processes on the same ports, each with its own models,
batchers, streams and tracks, under a supervisor that starts them, restarts one that dies, drains
them all on SIGTERM and reports their metrics as one (prometheus_client's multiprocess mode).

The ports are shared with SO_REUSEPORT: the kernel spreads new connections over the workers, so a
stream lives, with its tracks, in the process that accepted it. The supervisor holds each port bound
(not listening) for the whole run, so that the port is the service's while workers come and go.
Readiness is the whole service's: a worker answers ready (HTTP /readyz, gRPC health) once every
worker is (a marker file each, in the metrics folder). Where the workers own the CPUs, each runs on
CPUs of its own (the setting cpu_affinity: worker_cpus, pin_worker).
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import math
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from types import FrameType

log = logging.getLogger("repnet.server")

WORKER_ENV = "REPNET_WORKER"  # "i/n" in a worker: its index and the number of workers
METRICS_ENV = "PROMETHEUS_MULTIPROC_DIR"  # prometheus_client's multiprocess folder
SUPERVISOR_ENV = "REPNET_SUPERVISOR_PID"  # in a worker: the process that started it
CPUS_ENV = "REPNET_WORKER_CPUS"  # in a worker: the CPUs its threads run on, comma-separated (unset: any)
PR_SET_PDEATHSIG = 1  # Linux prctl(2): the signal a process gets when its parent dies
RESTART_DELAY_S = 1.0  # before a worker that died is started again
START_TIMEOUT_S = 120.0  # a worker not ready by then stops the start


CPU_MAX = Path("/sys/fs/cgroup/cpu.max")  # cgroup v2: "QUOTA PERIOD" in microseconds, or "max PERIOD"


def allowed_cpus() -> list[int]:
    """The CPUs this process may run on (its affinity), in order."""
    if hasattr(os, "sched_getaffinity"):
        return sorted(os.sched_getaffinity(0))
    return list(range(os.cpu_count() or 1))


def usable_cpus(cpu_max: Path = CPU_MAX) -> int:
    """The CPUs this process may run on: its affinity, capped by the cgroup's CPU quota (a container's
    CPU limit), rounded up; at least 1."""
    count = len(allowed_cpus())
    with contextlib.suppress(OSError, ValueError):
        quota, period = cpu_max.read_text().split()[:2]
        if quota != "max":
            count = min(count, math.ceil(int(quota) / int(period)))
    return max(1, count)


def worker_cpus(count: int, mode: str, allowed: Sequence[int], usable: int) -> list[tuple[int, ...] | None]:
    """The CPUs each of `count` workers runs on (None: wherever the kernel puts it), for the setting
    `cpu_affinity` (`mode`): `on`, worker i gets the i-th of the `allowed` CPUs (in turn, when the
    workers are more), or its i-th share of them when they are more than the workers; `auto`, the
    same only when the workers are exactly as many as the allowed CPUs and `usable` (a container's
    CPU limit included) is not below them, so that each worker owns a CPU; `off`, none."""
    cpus = list(allowed)
    if mode == "off" or count < 2 or not cpus:
        return [None] * count
    if mode == "auto" and (count != len(cpus) or usable < len(cpus)):
        return [None] * count
    if count >= len(cpus):
        return [(cpus[i % len(cpus)],) for i in range(count)]
    share = len(cpus) // count
    return [tuple(cpus[i * share : (i + 1) * share]) for i in range(count)]


def pin_worker() -> None:
    """In a worker: run every thread of this process, and every thread it starts later, on the CPUs
    its supervisor chose (CPUS_ENV), if it chose any."""
    value = os.environ.get(CPUS_ENV, "")
    if not value or not hasattr(os, "sched_setaffinity"):
        return
    cpus = tuple(int(c) for c in value.split(","))
    try:
        threads = [int(t) for t in os.listdir("/proc/self/task")]
    except OSError:
        threads = [0]  # this thread: the others inherit its affinity when they start
    for thread in threads:
        with contextlib.suppress(ProcessLookupError):  # a thread that ended meanwhile
            os.sched_setaffinity(thread, cpus)


@dataclass(frozen=True)
class Peers:
    """The workers of one service, as a worker sees them: a ready marker file each in `folder`."""

    folder: Path
    index: int
    count: int

    @classmethod
    def from_env(cls) -> Peers | None:
        """This worker's peers (None outside a supervised worker)."""
        value, folder = os.environ.get(WORKER_ENV, ""), os.environ.get(METRICS_ENV, "")
        if not value or not folder:
            return None
        index, _, count = value.partition("/")
        return cls(Path(folder), int(index), int(count))

    def _marker(self, index: int) -> Path:
        return self.folder / f"ready-{index}"

    def mark_ready(self, ready: bool) -> None:
        """Say whether this worker serves."""
        if ready:
            self._marker(self.index).touch()
        else:
            self._marker(self.index).unlink(missing_ok=True)

    def all_ready(self) -> bool:
        """Every worker serves."""
        return all(self._marker(k).exists() for k in range(self.count))

    def failed(self, message: str) -> None:
        """Say why this worker could not start (the supervisor repeats it as its own)."""
        (self.folder / f"failed-{self.index}").write_text(message)

    def why_failed(self, index: int) -> str | None:
        """Why worker `index` could not start, if it said."""
        path = self.folder / f"failed-{index}"
        return path.read_text() if path.exists() else None


def follow_supervisor() -> None:
    """In a worker: SIGTERM (a drain) when the supervisor dies, however it died, even SIGKILL, so that
    no worker outlives it holding the ports (Linux prctl; elsewhere, nothing)."""
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, int(signal.SIGTERM))
    supervisor = os.environ.get(SUPERVISOR_ENV, "")
    if supervisor.isdigit() and os.getppid() != int(supervisor):  # it died before prctl
        os.kill(os.getpid(), signal.SIGTERM)


def reuse_port_socket(host: str, port: int, backlog: int = 2048) -> socket.socket:
    """A TCP socket bound to host:port with SO_REUSEPORT (the workers share the port), listening."""
    family, kind, proto, _, address = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0]
    sock = socket.socket(family, kind, proto)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
    sock.bind(address)
    sock.listen(backlog)
    return sock


def reserve(host: str, port: int) -> socket.socket:
    """Hold host:port for the service (bound with SO_REUSEPORT, not listening: no connection comes to
    it); port 0 picks a free one. OSError when another program holds the port."""
    family, kind, proto, _, address = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0]
    sock = socket.socket(family, kind, proto)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
    try:
        sock.bind(address)
    except OSError:
        sock.close()
        raise
    return sock


SERVE = ("repnet", "serve")  # what a worker runs: python -m repnet serve


class Supervisor:
    """Runs `count` workers of `python -m <module>` (`repnet serve`) with `argv` on the ports it
    reserved."""

    def __init__(
        self,
        argv: Sequence[str],
        count: int,
        host: str,
        ports: tuple[int, int],
        grace_s: float,
        module: Sequence[str] = SERVE,
        cpus: Sequence[tuple[int, ...] | None] = (),
    ) -> None:
        self.argv = list(argv)
        self.cpus = list(cpus) or [None] * count  # each worker's CPUs (worker_cpus)
        self.module = list(module)
        self.count = count
        self.grace_s = grace_s
        self.held = [reserve(host, p) for p in ports]  # OSError: a port is taken
        self.ports = tuple(int(s.getsockname()[1]) for s in self.held)
        self.folder = Path(tempfile.mkdtemp(prefix="repnet-metrics-"))
        self.workers: dict[int, subprocess.Popen[bytes]] = {}
        self.signalled: set[int] = set()  # pids sent SIGTERM: once each (a second signal aborts a drain)
        self.stopping = False

    def _start(self, index: int) -> None:
        http, grpc_port = self.ports
        env = {**os.environ, WORKER_ENV: f"{index}/{self.count}", METRICS_ENV: str(self.folder)}
        env[SUPERVISOR_ENV] = str(os.getpid())
        cpus = self.cpus[index]
        if cpus is None:
            env.pop(CPUS_ENV, None)
        else:
            env[CPUS_ENV] = ",".join(map(str, cpus))
        # onnxruntime's threads: the CPUs shared out between the workers, unless set (flag or variable)
        env.setdefault("REPNET_INTRA_OP_THREADS", str(max(1, usable_cpus() // self.count)))
        command = [sys.executable, "-m", *self.module, *self.argv, "--workers", "1"]
        command += ["--http-port", str(http), "--grpc-port", str(grpc_port)]
        self.workers[index] = subprocess.Popen(command, env=env)

    def run(self) -> int:
        """Start the workers, wait for SIGTERM or SIGINT (restarting a worker that dies once all
        started), drain them; 0 when every worker exited cleanly."""
        signal.signal(signal.SIGTERM, self._on_signal)
        signal.signal(signal.SIGINT, self._on_signal)
        log.info("starting %d workers on HTTP :%d and gRPC :%d", self.count, *self.ports)
        if any(c is not None for c in self.cpus):
            placed = ", ".join(f"{i}: {','.join(map(str, c or ()))}" for i, c in enumerate(self.cpus))
            log.info("each worker on CPUs of its own (cpu_affinity): %s", placed)
        for index in range(self.count):
            if not self.stopping:
                self._start(index)
        try:
            if not self._wait_started():
                if not self.stopping:
                    return 1
            status = self._watch()
        finally:
            self._stop_all()
            self._report()
            for sock in self.held:
                sock.close()
            shutil.rmtree(self.folder, ignore_errors=True)
        return status

    def _wait_started(self) -> bool:
        """Wait until every worker is ready; False when one exits first, takes too long or a signal
        came first (then the workers drain like a started service's)."""
        peers = Peers(self.folder, 0, self.count)
        deadline = time.monotonic() + START_TIMEOUT_S
        while not peers.all_ready():
            for index, process in self.workers.items():
                if process.poll() is not None:
                    why = peers.why_failed(index) or f"worker {index} exited with {process.returncode}"
                    log.error("cannot start: %s", why)
                    return False
            if self.stopping:
                return False
            if time.monotonic() > deadline:
                log.error("cannot start: not every worker was ready within %.0f s", START_TIMEOUT_S)
                return False
            time.sleep(0.05)
        log.info("all %d workers ready", self.count)
        return True

    def _watch(self) -> int:
        """Until a signal: start again any worker that died. The workers' exit status at the end."""
        while not self.stopping:
            for index, process in list(self.workers.items()):
                if process.poll() is not None and not self.stopping:
                    log.error("worker %d (pid %d) exited with %d: starting it again", index, process.pid,
                              process.returncode)  # fmt: skip
                    self._forget(index, process.pid)
                    time.sleep(RESTART_DELAY_S)
                    self._start(index)
            time.sleep(0.1)
        return self._drain()

    def _on_signal(self, signum: int, frame: FrameType | None) -> None:
        log.info("received %s: draining %d workers", signal.Signals(signum).name, self.count)
        self.stopping = True
        self._signal_all()

    def _signal_all(self) -> None:
        for process in self.workers.values():
            if process.poll() is None and process.pid not in self.signalled:
                self.signalled.add(process.pid)
                process.send_signal(signal.SIGTERM)

    def _drain(self) -> int:
        """Wait for the workers to finish what they accepted; the worst exit status."""
        self._signal_all()  # any started after the signal
        deadline = time.monotonic() + self.grace_s + 10.0
        status = 0
        for process in self.workers.values():
            try:
                code = process.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                process.kill()
                code = process.wait()
            if code == -signal.SIGTERM and process.pid in self.signalled:
                code = 0  # stopped by our signal before it served: nothing accepted, nothing lost
            status = status or (code if code > 0 else 0 if code == 0 else 1)
        return status

    def _stop_all(self) -> None:
        self._signal_all()
        for process in self.workers.values():
            try:
                process.wait(self.grace_s + 10.0)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()

    def _forget(self, index: int, pid: int) -> None:
        """A worker that is gone: not ready, its live gauges no longer counted."""
        Peers(self.folder, index, self.count).mark_ready(False)
        from prometheus_client import multiprocess

        multiprocess.mark_process_dead(pid, str(self.folder))  # type: ignore[no-untyped-call]

    def _report(self) -> None:
        """The requests every worker answered, as one line (each worker logs its own too)."""
        from repnet.server.metrics import worker_metrics

        registry = worker_metrics(str(self.folder))
        counts = [
            f"{s.labels['transport']} {s.labels['method']} {s.labels['outcome']}={s.value:.0f}"
            for family in registry.collect()
            if family.name == "repnet_requests"
            for s in family.samples
            if s.name == "repnet_requests_total"
        ]
        log.info("stopped; requests answered: %s", ", ".join(sorted(counts)) or "none")
