"""One pass over a batch of jobs (runtime.pipeline.run_jobs): the streams' tracked poses of a batch
are pushed, windowed and answered together, and each stream gets what it gets alone."""

from __future__ import annotations

import gc
import weakref

import numpy as np
import pytest

from repnet.core.errors import LiftError
from repnet.core.inputs import Limits, PoseInput
from repnet.runtime.batchers import LiftBatcher
from repnet.runtime.lifter import Lifter
from repnet.runtime.pipeline import Job, Lifted, StreamTracks, TrackedPose, run_jobs, split_job
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


def crowd_job(tracks: StreamTracks, clips: list[np.ndarray], frame: int) -> Job:
    """One frame of a stream: a tracked person per clip, then two untracked poses and a pose that
    breaks an input rule (3 of 17 joints visible)."""
    visible = np.ones(17, bool)
    poses = [PoseInput(c[frame], visible, None, "h36m17", None) for c in clips]
    poses += [PoseInput(clips[k][frame] + 40.0, visible, None, "h36m17", None) for k in range(2)]
    poses.append(PoseInput(clips[0][frame], np.arange(17) < 3, None, "h36m17", None))
    tracked: list[TrackedPose | None] = [
        TrackedPose(f"p{k}", frame, 30.0, f"people[{k}].pose") for k in range(len(clips))
    ]
    return Job(finish=lambda lifted: lifted, poses=poses, tracks=tracks, tracked=[*tracked, None, None, None])


def test_a_frame_of_more_people_than_a_run_holds_is_lifted_in_parts_as_in_one_pass(
    lifter: Lifter, causal: TemporalLifter
) -> None:
    """A frame whose tracked people cost more than a run (max_batch 16: two tracked people a run)
    is queued in parts that run in order, and gets what one pass gives it: every track's causal
    answer, the stream's track limit (4) refusing the same people, errors and violations named within
    the whole frame."""
    clips = [clip(seed, 6) for seed in range(6)]
    whole, parted = stream(causal), stream(causal)
    engine = LiftBatcher(lifter, None, max_batch=16, max_wait_s=0.0, queue_size=256)
    try:
        for frame in range(6):
            job = crowd_job(whole, clips, frame)
            parts = split_job(job, 16)
            assert parts is not None and [len(p) for p in parts.parts] == [2, 2, 2, 3]
            one: Lifted = run_jobs(lifter, [job], Limits(), 256).answers[0]
            got: Lifted = engine.run(crowd_job(parted, clips, frame), "test")
            assert sorted(got.errors) == sorted(one.errors) == [4, 5]  # rows of p4, p5: over the limit
            assert [v.pose for found in got.prepared.violations for v in found] == [8]
            assert got.prepared.violations == one.prepared.violations
            assert got.replies is not None and one.replies is not None
            np.testing.assert_array_equal(got.replies.columns["temporal"], one.replies.columns["temporal"])
            assert got.replies.columns["temporal"][:4].all()  # p0-p3: their tracks' causal answers
            np.testing.assert_allclose(
                got.replies.columns["pose_3d_camera"], one.replies.columns["pose_3d_camera"], atol=1e-2
            )
    finally:
        engine.close(10)


def test_a_pose_refused_by_its_streams_track_limit_leaves_no_garbage_for_the_collector(
    lifter: Lifter, causal: TemporalLifter
) -> None:
    """The refusal is kept as the pose's answer without its traceback, which tied the pass's frame
    and every refusal in it into a cycle: under frames of 1,024 tracked people, the collector's full
    collections then took 110-137 ms of a worker's interpreter lock each."""
    tracks = StreamTracks(TrackTable(causal.contract, 1, 60.0, TrackBudget(16)), causal)
    clips = [clip(seed, 1) for seed in range(3)]
    gc.disable()
    try:
        lifted: Lifted = run_jobs(lifter, [crowd_job(tracks, clips, 0)], Limits(), 256).answers[0]
        assert sorted(lifted.errors) == [1, 2]  # p1, p2: over the stream's one track
        assert [v.code for v in lifted.errors[1].violations] == ["too_many_tracks"]
        refusals = [weakref.ref(err) for err in lifted.errors.values()]
        del lifted
        assert [r() for r in refusals] == [None, None]  # freed at once, not by the collector
    finally:
        gc.enable()


def test_a_jobs_refusal_leaves_no_garbage_for_the_collector(lifter: Lifter) -> None:
    """A job refused by its own finish (a pose that breaks a rule: InvalidKeypoints) is answered with
    that error, without the traceback that tied the pass's frame, and with it every array of the
    batch, into a cycle for the collector (the adapters check most rules before a job is queued, so
    this was rare; a stream group's failure is kept the same way)."""

    def refuse(lifted: Lifted) -> None:
        lifted.prepared.check()

    poses = [PoseInput(clip(0, 1)[0], np.arange(17) < 3, None, "h36m17", None)]
    gc.disable()
    try:
        batch = run_jobs(lifter, [Job(finish=refuse, poses=poses)], Limits(), 256)
        (refusal,) = batch.answers
        assert isinstance(refusal, LiftError) and refusal.violations[0].code == "too_few_visible"
        seen = weakref.ref(refusal)
        del batch, refusal
        assert seen() is None  # freed at once, not by the collector
    finally:
        gc.enable()
