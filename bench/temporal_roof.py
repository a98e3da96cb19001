"""The raw-model roof of a tracked pose for bench.temporal_load: both models per tracked pose, batch by
batch, with no server around them."""

from __future__ import annotations

import numpy as np

from bench.roof import RoofRow, measure_roof, time_calls
from bench.stats import latency_summary
from bench.tracked import (
    FPS,
    moving_clip,
)
from repnet.runtime.lifter import Lifter
from repnet.runtime.plans import camera_poses
from repnet.runtime.temporal import OUTPUT, Contract, TemporalLifter, Windows
from repnet.runtime.tracks import Observation, Track, track_capacity
from repnet.server.app import load_lifter
from repnet.server.config import Settings

ROOF_BATCHES = (1, 8, 64, 256)


def clip_windows(lifter: Lifter, contract: Contract, count: int, fps: float = FPS) -> Windows:
    """The causal windows of `count` consecutive frames of one tracked person (a moving clip lifted
    by the single-frame model, pushed into a Track as a stream pushes it)."""
    points = moving_clip(count)
    visible = np.ones(points.shape[:2], bool)
    prediction = lifter.lift(points, visible)
    poses = camera_poses(prediction, np.arange(count))
    track = Track(track_capacity(contract, fps), fps)
    windows = []
    for frame in range(count):
        track.push(frame, Observation(poses[frame], points[frame], np.ones(17, np.float32)))
        windows.append(track.window(contract))
    return Windows.join(windows, causal=True)


def temporal_roof(
    settings: Settings, batches: tuple[int, ...], duration: float
) -> tuple[list[RoofRow], Contract]:
    """Raw onnxruntime runs of the causal model (the service's session settings) at each batch size,
    on real windows at 30 fps; with the single-frame model's session.run at the same sizes."""
    rows = measure_roof(settings, batches, duration, with_lifter=False)
    temporal = TemporalLifter.load(settings.causal_model_path, settings)
    windows = clip_windows(load_lifter(settings), temporal.contract, max(batches))
    for batch in batches:
        part = windows.slice(0, batch)
        feeds = {
            "poses": part.poses,
            "keypoints_2d": part.keypoints_2d,
            "visibility": part.visibility,
            "fps": part.fps,
        }

        def run(feeds: dict[str, np.ndarray] = feeds) -> None:
            temporal.session.run([OUTPUT], feeds)

        calls, seconds, laps = time_calls(run, duration)
        rows.append(RoofRow("temporal session.run", batch, calls, seconds, latency_summary(laps)))
    return rows, temporal.contract


def per_pose_roof(rows: list[RoofRow]) -> dict[int, dict[str, float]]:
    """Per batch size: frames/s of the single-frame model, of the temporal model, and of both per
    tracked pose (1 / (1/a + 1/b): a tracked pose costs one run of each)."""
    out: dict[int, dict[str, float]] = {}
    for r in rows:
        model = "temporal" if r.what.startswith("temporal") else "single"
        out.setdefault(r.batch, {})[model] = r.frames_per_s
    for values in out.values():
        if "temporal" in values and "single" in values:
            values["both"] = 1 / (1 / values["single"] + 1 / values["temporal"])
    return out
