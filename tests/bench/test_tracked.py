"""bench.tracked: the moving people, their LiftFrame bytes and the answer checks of the temporal benches."""

from __future__ import annotations

import numpy as np

from bench.tracked import (
    CYCLE,
    Crowd,
    Load,
    expect_people,
    expect_pose,
    moving_clip,
    parse_gauges,
    people_entry,
    pose_parts,
    result_of,
    single_frame,
)
from repnet._proto.repnet.v1 import lifter_pb2


def test_a_moving_clip_moves_smoothly_and_closes_its_loop() -> None:
    clip = moving_clip(CYCLE, seed=2)
    assert clip.shape == (CYCLE, 17, 2) and clip.dtype == np.float32
    steps = np.linalg.norm(np.diff(np.concatenate([clip, clip[:1]]), axis=0), axis=-1)  # px per frame
    assert steps.max() < 15 and steps[:, 3].mean() > 1  # the feet move, nothing jumps, not even at the loop
    assert not np.allclose(moving_clip(seed=0), moving_clip(seed=1))


def test_frames_are_the_header_and_the_pose_merged() -> None:
    parts = pose_parts(moving_clip(4))
    tracked = lifter_pb2.LiftFrame.FromString(single_frame(parts, 6, "cam-1", fps=25))
    assert (tracked.frame_id, tracked.track_id, tracked.fps) == (6, "cam-1", 25.0)
    assert list(tracked.pose.keypoints) == list(lifter_pb2.LiftFrame.FromString(parts[2]).pose.keypoints)
    untracked = lifter_pb2.LiftFrame.FromString(single_frame(parts, 0))
    assert untracked.track_id == "" and untracked.fps == 0 and len(untracked.pose.keypoints) == 34


def test_a_crowd_frame_carries_one_entry_per_track_id() -> None:
    ids = ["a", "b" * 200, "c"]  # a long id: its length takes two varint bytes
    frame = lifter_pb2.LiftFrame.FromString(Crowd.of(2).frame(9, ids))
    assert frame.frame_id == 9 and frame.fps == 30 and not frame.HasField("pose")
    assert [p.track_id for p in frame.people] == ids
    assert all(len(p.pose.keypoints) == 34 for p in frame.people)
    assert list(frame.people[0].pose.keypoints) == list(
        frame.people[2].pose.keypoints
    )  # person 2 is person 0
    entry = lifter_pb2.LiftFrame.FromString(people_entry("x", lifter_pb2.TrackedPose().SerializeToString()))
    assert [p.track_id for p in entry.people] == ["x"]


def answer(frame_id: int, temporal: bool = True, people: int = 0, error: bool = False) -> bytes:
    result = lifter_pb2.LiftFrameResult(frame_id=frame_id)
    pose = lifter_pb2.PoseResult(pose_3d=[0.0] * 51, temporal=temporal)
    if error:
        result.error.message = "no"
    elif people:
        for k in range(people):
            result.people.add(track_id=str(k), pose=pose)
    else:
        result.pose.CopyFrom(pose)
    return result.SerializeToString()


def test_checks_want_the_frame_id_and_a_temporal_pose() -> None:
    check = expect_pose(temporal=True)
    assert check(answer(3), 3)
    assert (
        not check(answer(4), 3)
        and not check(answer(3, temporal=False), 3)
        and not check(answer(3, error=True), 3)
    )
    assert expect_pose(temporal=False)(answer(3, temporal=False), 3)
    assert expect_pose(temporal=True, every=10)(answer(0, error=True), 7)  # not parsed
    people = expect_people(2)
    assert people(answer(5, people=2), 5) and not people(answer(5, people=1), 5)


def test_gauges_are_read_from_the_metrics_page() -> None:
    page = "# HELP repnet_open_tracks x\nrepnet_open_tracks 12.0\nrepnet_track_state_bytes 1.5e+06\nother 3\n"
    assert parse_gauges(page) == {"open_tracks": 12.0, "track_state_bytes": 1.5e6}


def test_a_result_takes_the_cpu_of_its_window() -> None:
    load = Load(10.0, 12.0, latencies=[0.001, 0.002], completed=60, sent=61)
    load.cpu = {"server": 1.0, "client": 0.5, "machine": 3.0, "wall": 2.0}
    result = result_of("x", 2, 1, load, offered=60)
    assert result.frames_per_s == 30 and result.server_cpu == 0.5 and result.client_cpu == 0.25
    assert result.extra["other_cpu"] == 0.75 and result.extra["sent"] == 61 and result.extra["offered"] == 60
