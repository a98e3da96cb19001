"""A client that uses the service normally while an attack runs (bench.memory_attacks): one pose
every 20 ms on its own keep-alive connection, and /readyz on a fresh connection every 0.25 s; what
it saw, in figures and in one line."""

from __future__ import annotations

import json
import threading
import time
from typing import Any

import httpx

from bench.overload import _probe_once
from bench.server import ServiceProcess
from bench.stats import latency_summary, sample_poses

VICTIM_EVERY_S = 0.02
READYZ_EVERY_S = 0.25
JSON = {"content-type": "application/json"}
POSE = sample_poses(64)[0]  # the pose it sends (the first of bench.memory_attacks' poses)


class Bystander:
    """A client that uses the service normally while an attack runs: one pose every 20 ms on its own
    keep-alive connection, and /readyz on a fresh connection every 0.25 s."""

    def __init__(self, service: ServiceProcess) -> None:
        self.service = service
        self.lift_s: list[float] = []
        self.statuses: list[int] = []
        self.readyz_s: list[float | None] = []
        self._stop = threading.Event()
        body = {"poses": [{"keypoints": POSE.round(1).tolist()}]}
        self._body = json.dumps(body).encode()
        self._threads = [threading.Thread(target=self._lift), threading.Thread(target=self._ready)]

    def _lift(self) -> None:
        with httpx.Client(timeout=30) as http:
            while not self._stop.wait(VICTIM_EVERY_S):
                start = time.perf_counter()
                try:
                    status = http.post(
                        self.service.url + "/lift", content=self._body, headers=JSON
                    ).status_code
                except httpx.HTTPError:
                    status = 0
                self.lift_s.append(time.perf_counter() - start)
                self.statuses.append(status)

    def _ready(self) -> None:
        while not self._stop.wait(READYZ_EVERY_S):
            self.readyz_s.append(_probe_once("127.0.0.1", self.service.http_port))

    def __enter__(self) -> Bystander:
        for thread in self._threads:
            thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        for thread in self._threads:
            thread.join()

    def summary(self) -> dict[str, Any]:
        """The bystander's lift latencies (ms), how many were not 200, and the worst /readyz (None:
        one did not answer within the probe's timeout)."""
        answered = [s for s in self.readyz_s if s is not None]
        return {
            "lift_ms": latency_summary(self.lift_s) if self.lift_s else None,
            "lift_not_200": sum(s != 200 for s in self.statuses),
            "lifts": len(self.statuses),
            "readyz_worst_ms": max(answered) * 1000 if answered else None,
            "readyz_missed": len(self.readyz_s) - len(answered),
        }


def bystanders_line(seen: dict[str, Any]) -> str:
    """What the bystander saw, in one line."""
    lift = seen["lift_ms"] or {"p50": float("nan"), "p99": float("nan")}
    worst = "none answered" if seen["readyz_worst_ms"] is None else f"{seen['readyz_worst_ms']:.0f} ms"
    return (
        f"{seen['lifts']} lifts, p50 {lift['p50']:.1f} / p99 {lift['p99']:.1f} ms, "
        f"{seen['lift_not_200']} not 200; worst /readyz {worst}, {seen['readyz_missed']} missed"
    )
