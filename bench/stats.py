"""Benchmark bookkeeping: latency summaries, sample poses, markdown tables and JSON output."""

from __future__ import annotations

import json
import logging
import os
import platform
import time
from collections.abc import Callable
from dataclasses import dataclass, field, fields, is_dataclass
from pathlib import Path
from typing import Any

import numpy as np

from bench.server import cpu_seconds
from repnet.core.inputs import EXAMPLE_KEYPOINTS

log = logging.getLogger(__name__)

# A person in mid-stride seen from 4.5 m (h36m17, px): the service's example person.
BASE_POSE = np.array(EXAMPLE_KEYPOINTS)


def sample_poses(n: int, seed: int = 0) -> np.ndarray:
    """(n, 17, 2) float32 plausible poses: the base pose moved, scaled and shaken."""
    rng = np.random.default_rng(seed)
    scale = rng.uniform(0.6, 1.6, (n, 1, 1))
    shift = rng.uniform(-200, 200, (n, 1, 2))
    return ((BASE_POSE - 512) * scale + 512 + shift + rng.normal(0, 2, (n, 17, 2))).astype(np.float32)


@dataclass
class Result:
    """One measured configuration."""

    name: str  # e.g. "HTTP /lift, 1 pose"
    concurrency: int
    frames: int  # poses answered in the measured window
    calls: int  # requests (or stream frames) answered in the window
    seconds: float
    latency_ms: dict[str, float] = field(default_factory=dict)  # p50, p90, p99, mean
    errors: int = 0
    server_cpu: float | None = None  # server process CPU seconds per wall second (2.0 = both cores)
    client_cpu: float | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def frames_per_s(self) -> float:
        """Frames answered per second of the window."""
        return self.frames / self.seconds if self.seconds else 0.0


@dataclass
class Tally:
    """Counts of one measured window [start, stop): latencies of calls sent in it, calls done in it."""

    start: float
    stop: float
    latencies: list[float] = field(default_factory=list)
    completed: int = 0
    errors: int = 0

    def record(self, sent: float, done: float, ok: bool = True) -> None:
        """Count a call sent at `sent` and answered at `done`: its latency if it was sent in the window
        and answered (an error is counted apart: a fast refusal is not a fast answer), and as completed
        if it was answered in the window (an error is not throughput)."""
        if self.start <= sent < self.stop:
            if ok:
                self.latencies.append(done - sent)
            self.errors += not ok
        if ok and self.start <= done < self.stop:
            self.completed += 1


def measured(
    name: str, concurrency: int, frames_per_call: int, server_pid: int, run: Callable[[], Tally]
) -> Result:
    """Run one load and build its Result, with the server's and this process's CPU use."""
    cpu0, client0, wall0 = cpu_seconds(server_pid), time.process_time(), time.perf_counter()
    tally = run()
    wall = time.perf_counter() - wall0
    return Result(
        name=name,
        concurrency=concurrency,
        frames=tally.completed * frames_per_call,
        calls=tally.completed,
        seconds=tally.stop - tally.start,
        latency_ms=latency_summary(tally.latencies),
        errors=tally.errors,
        server_cpu=(cpu_seconds(server_pid) - cpu0) / wall,
        client_cpu=(time.process_time() - client0) / wall,
    )


def latency_summary(seconds: list[float] | np.ndarray) -> dict[str, float]:
    """p50, p90, p99 and mean of latencies in seconds, as milliseconds."""
    ms = np.asarray(seconds, dtype=np.float64) * 1e3
    if ms.size == 0:
        return {}
    p50, p90, p99 = np.percentile(ms, [50, 90, 99])
    return {"p50": float(p50), "p90": float(p90), "p99": float(p99), "mean": float(ms.mean())}


def machine() -> dict[str, Any]:
    """CPU model, core count, Python version and platform of this machine."""
    cpu = ""
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), "")
    except OSError:
        pass
    return {
        "cpus": os.cpu_count(),
        "cpu": cpu,
        "python": platform.python_version(),
        "platform": platform.platform(),
    }


def fmt(value: float | None, digits: int = 2) -> str:
    """`value` with thousands separators and `digits` decimals; a dash for None."""
    return "—" if value is None else f"{value:,.{digits}f}"


def results_table(results: list[Result], roof_best: float) -> str:
    """One markdown row per result, with its throughput as a fraction of the roof's best."""
    lines = [
        "| measurement | conc. | frames/s | × roof best | p50 ms | p90 ms | p99 ms | errors | server CPU |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in results:
        lat = r.latency_ms
        lines.append(
            f"| {r.name} | {r.concurrency} | {fmt(r.frames_per_s, 0)} | {fmt(r.frames_per_s / roof_best, 3)} "
            f"| {fmt(lat.get('p50'))} | {fmt(lat.get('p90'))} | {fmt(lat.get('p99'))} | {r.errors} "
            f"| {fmt(r.server_cpu)} |"
        )
    return "\n".join(lines)


DERIVED = (
    "frames_per_s",
    "ms_per_call",
    "roof_best",
    "roof_batch1_ms",
    "targets",
)  # properties worth keeping


def report(result: Any, out: Path, render: Callable[[Any], str]) -> int:
    """The end of a benchmark's main(): write the result as JSON, print its markdown; exit code 0."""
    write_json(out, result)
    print(render(result))
    log.info("wrote %s", out)
    return 0


def write_json(path: Path, payload: Any) -> None:
    """Write `payload` as indented JSON, creating the folder."""
    path.parent.mkdir(parents=True, exist_ok=True)

    def default(value: Any) -> Any:
        if is_dataclass(value) and not isinstance(value, type):
            derived = {k: getattr(value, k) for k in DERIVED if hasattr(value, k)}
            return {**{f.name: getattr(value, f.name) for f in fields(value)}, **derived}
        if isinstance(value, Path):
            return str(value)
        if isinstance(value, np.generic):
            return value.item()
        raise TypeError(f"cannot write {type(value).__name__} as JSON")

    path.write_text(json.dumps(payload, indent=2, default=default) + "\n")
