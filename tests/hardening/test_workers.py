"""`repnet serve --workers 2`: two processes on the same ports under a supervisor; both serve, /metrics
adds them up, readiness is the whole service's, a worker that dies is started again, SIGTERM
drains every worker (nothing accepted is lost) and exits 0, and each worker runs on CPUs of its own
as `cpu_affinity` says."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import grpc
import httpx
import pytest

from bench.server import free_port, process_tree
from repnet._proto.repnet.v1 import lifter_pb2, lifter_pb2_grpc
from repnet.server.workers import Peers, allowed_cpus, usable_cpus, worker_cpus
from tests.conftest import POSE_2D

ROOT = Path(__file__).resolve().parents[2]
BODY = {"keypoints": POSE_2D.tolist()}


class Supervised:
    def __init__(self, tmp: Path, more_flags: tuple[str, ...] = ()) -> None:
        self.http, self.grpc = free_port(), free_port()
        self.log = tmp / "service.log"
        env = {**os.environ, "ORT_DISABLE_TELEMETRY": "1"}
        flags = ["--workers", "2", "--intra-op-threads", "1", "--host", "127.0.0.1"]
        flags += ["--http-port", str(self.http), "--grpc-port", str(self.grpc), "--shutdown-grace-s", "5"]
        flags += more_flags
        self.process = subprocess.Popen(
            [sys.executable, "-m", "repnet", "serve", *flags], cwd=ROOT, env=env,
            stdout=self.log.open("wb"), stderr=subprocess.STDOUT,
        )  # fmt: skip
        self.url = f"http://127.0.0.1:{self.http}"

    def ready(self, timeout: float = 90.0) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            assert self.process.poll() is None, self.log.read_text()[-3000:]
            try:
                if httpx.get(f"{self.url}/readyz", timeout=1).status_code == 200:
                    return
            except httpx.TransportError:
                pass
            time.sleep(0.1)
        raise AssertionError("not ready: " + self.log.read_text()[-3000:])

    def workers(self) -> list[int]:
        return [pid for pid in process_tree(self.process.pid) if pid != self.process.pid]

    def placed(self) -> dict[int, set[frozenset[int]]]:
        """Each worker's index: the CPU sets its threads may run on."""
        return {worker_index(pid): threads_cpus(pid) for pid in self.workers()}

    def restarted(self, pid: int) -> None:
        """Wait until the worker `pid` killed has been started again and the service is ready."""
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            found = self.workers()
            if len(found) == 2 and pid not in found:
                break
            time.sleep(0.1)
        assert pid not in self.workers() and len(self.workers()) == 2
        self.ready()


def worker_index(pid: int) -> int:
    """A worker's index, from its environment (REPNET_WORKER=i/n)."""
    environ = Path(f"/proc/{pid}/environ").read_bytes().split(b"\0")
    value = next(v for v in environ if v.startswith(b"REPNET_WORKER="))
    return int(value.split(b"=", 1)[1].split(b"/")[0])


def threads_cpus(pid: int) -> set[frozenset[int]]:
    """The CPU sets the threads of process `pid` may run on."""
    found = set()
    for task in os.listdir(f"/proc/{pid}/task"):
        try:
            found.add(frozenset(os.sched_getaffinity(int(task))))
        except ProcessLookupError:  # a thread that ended meanwhile
            pass
    return found


@pytest.fixture
def service(tmp_path: Path) -> Iterator[Supervised]:
    supervised = Supervised(tmp_path)
    try:
        supervised.ready()
        yield supervised
    finally:
        if supervised.process.poll() is None:
            supervised.process.kill()
            supervised.process.wait()


def lift_on_fresh_connections(url: str, count: int) -> list[int]:
    statuses = []
    for _ in range(count):  # a new connection each: the kernel spreads them over the workers
        with httpx.Client(base_url=url, timeout=30) as client:
            statuses.append(client.post("/lift", json=BODY).status_code)
    return statuses


def test_both_workers_serve_and_the_metrics_add_them_up_and_sigterm_drains_both(service: Supervised) -> None:
    assert len(service.workers()) == 2
    # cpu_affinity auto: each worker on a CPU of its own only where the workers are as many as the CPUs
    plan = worker_cpus(2, "auto", allowed_cpus(), usable_cpus())
    everywhere = frozenset(allowed_cpus())
    assert service.placed() == {i: {frozenset(plan[i] or everywhere)} for i in range(2)}
    assert lift_on_fresh_connections(service.url, 40) == [200] * 40
    with grpc.insecure_channel(f"127.0.0.1:{service.grpc}") as channel:
        stub = lifter_pb2_grpc.PoseLifterStub(channel)  # type: ignore[no-untyped-call]
        reply = stub.Lift(
            lifter_pb2.LiftRequest(poses=[lifter_pb2.Pose2D(keypoints=POSE_2D.ravel().tolist())])
        )
        assert len(reply.poses) == 1
    metrics = httpx.get(f"{service.url}/metrics", timeout=10).text
    assert 'repnet_requests_total{method="Lift",outcome="ok",transport="http"} 40.0' in metrics
    assert 'repnet_requests_total{method="Lift",outcome="ok",transport="grpc"} 1.0' in metrics
    workers = service.workers()
    service.process.send_signal(signal.SIGTERM)
    assert service.process.wait(30) == 0
    assert not any(Path(f"/proc/{pid}").exists() for pid in workers)
    log = service.log.read_text()
    per_worker = [
        int(n)
        for n in re.findall(r"\[worker \d\] [\w.]+: stopped; requests answered: http Lift ok=(\d+)", log)
    ]
    assert len(per_worker) == 2 and sum(per_worker) == 40 and min(per_worker) > 0, log[-3000:]
    total = re.findall(r"stopped; requests answered: (.*)", log)[-1]  # the supervisor's, last
    assert "http Lift ok=40" in total and "grpc Lift ok=1" in total
    assert "Warning" not in log, log[-3000:]  # prometheus_client's multiprocess mode had one per worker


def test_a_worker_that_dies_is_started_again_and_readiness_waits_for_it(service: Supervised) -> None:
    first, second = service.workers()
    os.kill(first, signal.SIGKILL)
    service.restarted(first)  # not ready while one is missing, ready once it is back
    assert second in service.workers()
    assert lift_on_fresh_connections(service.url, 10) == [200] * 10
    assert "worker 0" in service.log.read_text() or "worker 1" in service.log.read_text()


def test_with_cpu_affinity_on_each_worker_runs_on_cpus_of_its_own_after_a_restart_too(tmp_path: Path) -> None:
    supervised = Supervised(tmp_path, ("--cpu-affinity", "on"))
    try:
        supervised.ready()
        plan = worker_cpus(2, "on", allowed_cpus(), usable_cpus())
        wanted = {i: {frozenset(cpus)} for i, cpus in enumerate(plan) if cpus is not None}
        assert len(wanted) == 2 and supervised.placed() == wanted  # every thread, onnxruntime's and gRPC's
        if len(allowed_cpus()) > 1:
            assert not wanted[0] & wanted[1]
        first = next(pid for pid in supervised.workers() if worker_index(pid) == 0)
        os.kill(first, signal.SIGKILL)
        supervised.restarted(first)
        assert supervised.placed() == wanted
        assert lift_on_fresh_connections(supervised.url, 10) == [200] * 10
        assert "each worker on CPUs of its own" in supervised.log.read_text()
    finally:
        if supervised.process.poll() is None:
            supervised.process.kill()
            supervised.process.wait()


@pytest.mark.parametrize("after", ["starting 2 workers", "[worker 1] repnet.runtime.lifter: loaded model"])
def test_sigterm_while_the_workers_start_stops_them_all_with_status_0(tmp_path: Path, after: str) -> None:
    supervised = Supervised(tmp_path)
    try:
        deadline = time.monotonic() + 90
        while after not in (log := supervised.log.read_text()):
            assert supervised.process.poll() is None and time.monotonic() < deadline, log
            time.sleep(0.01)
        workers = supervised.workers()
        supervised.process.send_signal(signal.SIGTERM)
        assert supervised.process.wait(30) == 0, supervised.log.read_text()[-3000:]
        assert not any(Path(f"/proc/{pid}").exists() for pid in workers)
    finally:
        if supervised.process.poll() is None:
            supervised.process.kill()
            supervised.process.wait()


def test_no_worker_outlives_a_supervisor_killed_with_sigkill(service: Supervised) -> None:
    workers = service.workers()
    assert len(workers) == 2
    service.process.kill()
    service.process.wait()
    deadline = time.monotonic() + 30
    while any(Path(f"/proc/{pid}").exists() for pid in workers) and time.monotonic() < deadline:
        time.sleep(0.1)
    alive = [pid for pid in workers if Path(f"/proc/{pid}/cmdline").exists()]
    assert alive == [], service.log.read_text()[-3000:]
    with pytest.raises(httpx.TransportError):  # nothing holds the ports any more
        httpx.get(f"{service.url}/healthz", timeout=2)


def test_readiness_is_the_whole_services(tmp_path: Path) -> None:
    peers = [Peers(tmp_path, k, 2) for k in range(2)]
    peers[0].mark_ready(True)
    assert not peers[0].all_ready() and not peers[1].all_ready()
    peers[1].mark_ready(True)
    assert peers[0].all_ready() and peers[1].all_ready()
    peers[1].mark_ready(False)  # shutting down, or gone
    assert not peers[0].all_ready()


def test_the_default_is_one_worker_per_usable_cpu(tmp_path: Path) -> None:
    affinity = len(os.sched_getaffinity(0))
    assert 1 <= usable_cpus() <= affinity
    quota = tmp_path / "cpu.max"
    quota.write_text("150000 100000\n")  # a container limited to 1.5 CPUs: 2 workers
    assert usable_cpus(quota) == min(affinity, 2)
    quota.write_text("max 100000\n")
    assert usable_cpus(quota) == affinity


def test_cpu_affinity_gives_each_worker_cpus_of_its_own_only_where_it_should() -> None:
    two, four = [0, 1], [0, 1, 2, 3]
    assert worker_cpus(2, "auto", two, 2) == [(0,), (1,)]  # the workers own the CPUs
    assert worker_cpus(2, "auto", two, 1) == [None, None]  # a container limit below the CPUs
    assert worker_cpus(2, "auto", four, 4) == [None, None]  # fewer workers than CPUs
    assert worker_cpus(4, "auto", two, 2) == [None] * 4  # more workers than CPUs
    assert worker_cpus(2, "off", two, 2) == [None, None]
    assert worker_cpus(1, "on", two, 2) == [None]  # one worker: no supervisor, nothing to place
    assert worker_cpus(2, "on", four, 2) == [(0, 1), (2, 3)]  # a share each
    assert worker_cpus(2, "on", [0, 1, 2], 3) == [(0,), (1,)]
    assert worker_cpus(3, "on", [4, 7], 2) == [(4,), (7,), (4,)]  # in turn
