"""The roof: raw onnxruntime on the model with the service's session options, no service around it."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from bench.stats import latency_summary, sample_poses
from repnet.core.inputs import ModelInput, PoseInput
from repnet.core.keypoints import prepare_poses
from repnet.runtime.lifter import OUTPUTS
from repnet.runtime.replies import build_replies
from repnet.server.app import limits_of, load_lifter
from repnet.server.config import Settings

BATCHES: tuple[int, ...] = (1, 8, 64, 256, 1024)


@dataclass(frozen=True)
class RoofRow:
    """One roof measurement: calls of one kind at one batch size."""

    # "session.run" (the model alone) or "Lifter.lift" (Lifter.lift and build_replies: plus the
    # service's masking, checks and camera geometry, as a batch of the service costs them)
    what: str
    batch: int
    calls: int
    seconds: float
    latency_ms: dict[str, float]

    @property
    def frames_per_s(self) -> float:
        """Poses per second."""
        return self.batch * self.calls / self.seconds

    @property
    def ms_per_call(self) -> float:
        """Mean milliseconds per call."""
        return 1e3 * self.seconds / self.calls


def time_calls(
    call: Callable[[], None], duration: float, min_calls: int = 5
) -> tuple[int, float, list[float]]:
    """call() after three warm-up calls, for `duration` seconds and at least `min_calls` times: the
    calls, their total seconds and each one's."""
    for _ in range(3):  # warm-up: first runs allocate
        call()
    laps: list[float] = []
    start = time.perf_counter()
    while (now := time.perf_counter()) - start < duration or len(laps) < min_calls:
        call()
        laps.append(time.perf_counter() - now)
    return len(laps), sum(laps), laps


def measure_roof(
    settings: Settings,
    batches: tuple[int, ...] = BATCHES,
    duration: float = 2.0,
    with_lifter: bool = True,
) -> list[RoofRow]:
    """Frames/s and ms per call at each batch size, through the service's own session setup."""
    lifter = load_lifter(settings)  # the service's own session set-up
    rows = []
    for batch in batches:
        points = sample_poses(batch, seed=batch)
        visible = np.ones(points.shape[:2], np.float32)
        feeds = {"keypoints_2d": points, "visibility": visible}

        def run(feeds: dict[str, np.ndarray] = feeds) -> None:
            lifter.session.run(list(OUTPUTS), feeds)

        calls, seconds, laps = time_calls(run, duration)
        rows.append(RoofRow("session.run", batch, calls, seconds, latency_summary(laps)))
        if with_lifter:
            poses = [PoseInput(p, np.ones(len(p), bool)) for p in points]
            inputs = prepare_poses(poses, limits_of(settings)).check()

            def lift(inputs: ModelInput = inputs) -> None:
                build_replies(inputs, lifter.lift(inputs.keypoints_2d, inputs.visible))

            calls, seconds, laps = time_calls(lift, duration)
            rows.append(RoofRow("Lifter.lift", batch, calls, seconds, latency_summary(laps)))
    return rows


def roof_table(rows: list[RoofRow]) -> str:
    """Roof rows as a markdown table."""
    lines = [
        "| roof | batch | frames/s | ms per call | p99 ms |",
        "|---|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r.what} | {r.batch} | {r.frames_per_s:,.0f} | {r.ms_per_call:.3f} | "
            f"{r.latency_ms.get('p99', float('nan')):.3f} |"
        )
    return "\n".join(lines)
