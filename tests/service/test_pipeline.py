"""One pass over a batch of jobs (runtime.pipeline.run_jobs): the streams' tracked poses of a batch
are pushed, windowed and answered together, and each stream gets what it gets alone."""

from __future__ import annotations

import numpy as np
import pytest

from repnet.core.errors import LiftError
from repnet.core.inputs import Limits, PoseInput
from repnet.runtime.lifter import Lifter
from repnet.runtime.pipeline import Job, Lifted, StreamTracks, TrackedPose, run_jobs
from repnet.runtime.temporal import TemporalLifter
from repnet.runtime.tracks import TrackBudget, TrackTable
from repnet.server.config import Settings
from tests.conftest import POSE_3D, project


@pytest.fixture(scope="module")
def causal() -> TemporalLifter:
    return TemporalLifter.load(Settings().causal_model_path)


def clip(seed: int, frames: int) -> np.ndarray:
    """(frames, 17, 2) px: a person turning slowly in front of the camera (`seed`: where they start)."""
    start = 30.0 * seed
    return np.stack([project(POSE_3D, yaw_deg=start + 2.0 * f) for f in range(frames)]).astype(np.float32)


def stream(causal: TemporalLifter) -> StreamTracks:
    return StreamTracks(TrackTable(causal.contract, 4, 60.0, TrackBudget(16)), causal)


def frame_job(tracks: StreamTracks, points: np.ndarray, frame: int, fps: float, track: str = "a") -> Job:
    pose = PoseInput(points, np.ones(17, bool), None, "h36m17", None)
    return Job(
        finish=lambda lifted: lifted,
        poses=[pose],
        tracks=tracks,
        tracked=[TrackedPose(track, frame, fps, "pose")],
    )


def answers(lifted: Lifted) -> tuple[np.ndarray, bool, dict[int, LiftError]]:
    assert lifted.replies is not None
    return (
        lifted.replies.columns["pose_3d_camera"][0],
        bool(lifted.replies.columns["temporal"][0]),
        lifted.errors,
    )


def test_streams_batched_together_get_what_each_gets_alone(lifter: Lifter, causal: TemporalLifter) -> None:
    """Three streams at 25, 30 and 60 fps (windows of different lengths, padded in one run), lifted
    frame by frame in one batch, against each stream lifted in batches of its own."""
    rates = (25.0, 30.0, 60.0)
    clips = [clip(seed, 70) for seed in range(3)]
    together = [stream(causal) for _ in rates]
    alone = [stream(causal) for _ in rates]
    limits = Limits()
    for frame in range(70):
        jobs = [frame_job(s, c[frame], frame, fps) for s, c, fps in zip(together, clips, rates, strict=True)]
        batch = run_jobs(lifter, jobs, limits, 256)
        for k, fps in enumerate(rates):
            single = run_jobs(lifter, [frame_job(alone[k], clips[k][frame], frame, fps)], limits, 256)
            pose, temporal, errors = answers(batch.answers[k])
            pose_alone, temporal_alone, errors_alone = answers(single.answers[0])
            assert temporal and temporal_alone and not errors and not errors_alone
            # mm: onnxruntime's products of a row differ in the last bits with the batch's size (1e-3
            # mm seen); another track's window or a wrong pad would move it by many mm
            np.testing.assert_allclose(pose, pose_alone, atol=1e-2)


def test_a_refused_pose_fails_alone_and_the_batchs_other_streams_are_answered(
    lifter: Lifter, causal: TemporalLifter
) -> None:
    """A frame sent out of order is refused with a frame_order error named in its own job; the other
    stream of the same batch is answered by the temporal model."""
    limits = Limits()
    first, second = stream(causal), stream(causal)
    points = clip(0, 3)
    run_jobs(
        lifter, [frame_job(first, points[0], 5, 30.0), frame_job(second, points[0], 5, 30.0)], limits, 256
    )
    batch = run_jobs(
        lifter, [frame_job(first, points[1], 4, 30.0), frame_job(second, points[1], 6, 30.0)], limits, 256
    )
    refused, answered = batch.answers
    assert [v.code for v in refused.errors[0].violations] == ["frame_order"]
    assert answers(answered)[1] and not answered.errors
