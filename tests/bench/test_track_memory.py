"""bench.track_memory and bench.long_tracks: their bookkeeping, and tiny runs against a started server
(the plumbing: tracks opened, gauges read, every track freed at the end; not the figures)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from bench import long_tracks, track_memory
from bench.long_tracks import Frames, Rotation, lane_plan, tracks_opened
from repnet._proto.repnet.v1 import lifter_pb2
from repnet.runtime.tracks import track_bytes


def test_tracks_are_dealt_over_the_streams_and_keep_their_stream_as_more_open() -> None:
    assert track_memory.spread(5, 2) == [["t0", "t2", "t4"], ["t1", "t3"]]
    assert track_memory.spread(3, 2)[0][:2] == track_memory.spread(5, 2)[0][:2]


def test_memory_per_track_is_the_rss_added_between_track_counts() -> None:
    phases = [
        {"phase": "idle", "tracks": 0, "rss_mb": 90.0},
        {"phase": "0 tracks, streams open", "tracks": 0, "rss_mb": 100.0},
        {"phase": "100 tracks", "tracks": 100, "rss_mb": 110.0, "track_state_bytes": 100 * 2048},
        {"phase": "1000 tracks", "tracks": 1000, "rss_mb": 200.0, "track_state_bytes": 1000 * 2048},
        {"phase": "streams closed", "tracks": 0, "rss_mb": 150.0},
    ]
    rows = track_memory.per_track(phases)
    assert [(r["from"], r["to"]) for r in rows] == [(0, 100), (100, 1000)]
    assert rows[0]["rss_kb_per_track"] == pytest.approx(102.4) and rows[1]["gauge_kb_per_track"] == 2.0


def test_a_filled_track_takes_about_its_nbytes_in_python() -> None:
    measured = track_memory.python_track_bytes(50, count=20)
    assert track_bytes(50) <= measured < track_bytes(50) + 4096


def test_a_rotation_drops_each_slots_tracks_in_turn() -> None:
    rotation = Rotation(lane=1, slots=4, people=2, life=8)
    assert rotation.groups == 2 and rotation.frame(5) == (2, [2, 3])
    assert [rotation.first_life(j) for j in range(4)] == [2, 4, 6, 8]  # staggered
    assert [rotation.generation(0, f) for f in (0, 1, 2, 9, 10)] == [0, 0, 1, 1, 2]
    assert rotation.stream_frames(0, 0, 2) == 8 and rotation.stream_frames(1, 0, 2) == 16
    assert tracks_opened(rotation, 4) == 4 and tracks_opened(rotation, 6) == 5  # slot 0 took its 2nd track


def test_a_lanes_frames_carry_its_current_tracks() -> None:
    frames = Frames(Rotation(lane=0, slots=2, people=1, life=3))
    first = lifter_pb2.LiftFrame.FromString(frames.idle(0))
    later = lifter_pb2.LiftFrame.FromString(frames.idle(5))  # slot 1 at frame number 2
    assert (first.frame_id, first.track_id, first.fps) == (0, "l0-j0-g0", 30.0)
    assert (later.frame_id, later.track_id) == (2, "l0-j1-g0")
    assert lifter_pb2.LiftFrame.FromString(frames.idle(4)).track_id == "l0-j0-g1"
    crowd = Frames(Rotation(lane=2, slots=2, people=2, life=3))
    frame = lifter_pb2.LiftFrame.FromString(crowd.in_stream(4)(1))
    assert frame.frame_id == 1 and [p.track_id for p in frame.people] == ["l2-s4-j0", "l2-s4-j1"]


def test_both_drops_split_the_lanes() -> None:
    args = long_tracks.parse_args(["--tracks", "8", "--lanes", "4", "--frames", "100", "--warmup", "10"])
    assert [(drop, rank) for _, drop, rank in lane_plan(args)] == [
        ("stream", (0, 2)), ("stream", (1, 2)), ("idle", (0, 2)), ("idle", (1, 2)),
    ]  # fmt: skip


def test_a_tiny_track_memory_run_reads_the_gauges_and_frees_every_track(tmp_path: Path) -> None:
    out = tmp_path / "track_memory.json"
    argv = ["--tracks", "3,7", "--streams", "2", "--frames-per-track", "4", "--people", "2",
            "--untracked-frames", "2", "--out", str(out)]  # fmt: skip
    assert track_memory.main(argv) == 0
    found = json.loads(out.read_text())
    assert found["bad_answers"] == 0 and found["capacity"] > 0
    by = {p["phase"]: p for p in found["phases"]}
    assert by["3 tracks"]["open_tracks"] == 3 and by["7 tracks"]["open_tracks"] == 7
    assert by["7 tracks"]["track_state_bytes"] == 7 * found["track_nbytes"]
    assert by["streams closed"]["open_tracks"] == 0 and by["streams closed"]["track_state_bytes"] == 0


def test_a_tiny_long_run_opens_and_drops_tracks_and_ends_with_none_open(tmp_path: Path) -> None:
    out = tmp_path / "long_tracks.json"
    argv = ["--frames", "800", "--tracks", "4", "--lanes", "2", "--track-frames", "20", "--warmup", "200",
            "--sample-every", "200", "--track-idle-s", "0.2", "--out", str(out)]  # fmt: skip
    assert long_tracks.main(argv) == 0
    found = json.loads(out.read_text())
    assert found["frames"] == 800 and found["bad_answers"] == 0
    assert found["tracks_opened"] > 4 and found["streams_opened"] > 2  # dropped and replaced
    assert found["open_tracks"]["end"] == 0 and found["open_tracks"]["end_bytes"] == 0
    assert found["warmed_up"] and len(found["samples"]) >= 3
