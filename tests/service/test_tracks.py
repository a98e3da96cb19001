"""Tracks without a server: a track's ring is sized for its own frame rate and gives the same
windows as a larger one; the table's budget counts each track's bytes."""

from __future__ import annotations

import numpy as np
import pytest

from repnet.runtime.temporal import Contract
from repnet.runtime.tracks import (
    Observation,
    Track,
    TrackBudget,
    TrackLimitReached,
    TrackTable,
    clip_windows,
    track_bytes,
    track_capacity,
)

CONTRACT = Contract("causal", grid_fps=50.0, window=81, max_fps=60.0)  # the bundled causal model's


def seen(frame: int) -> Observation:
    rng = np.random.default_rng(frame)
    return Observation(
        rng.normal(size=(17, 3)).astype(np.float32),
        rng.normal(size=(17, 2)).astype(np.float32),
        (rng.random(17) > 0.1).astype(np.float32),
    )


def test_a_tracks_ring_holds_what_its_own_rate_needs() -> None:
    assert [track_capacity(CONTRACT, fps) for fps in (25, 30, 60, 120, 240)] == [41, 49, 97, 193, 385]
    # the newest frame and the q (K - 1) before it
    for fps in (25.0, 29.97, 50.0, 90.0, 240.0):
        q = CONTRACT.thinning(fps)
        assert track_capacity(CONTRACT, fps) == q * (CONTRACT.slots(fps / q) - 1) + 1


@pytest.mark.parametrize("fps", [30.0, 90.0, 240.0])
def test_a_small_ring_gives_the_windows_of_a_large_one(fps: float) -> None:
    small, large = Track(track_capacity(CONTRACT, fps), fps), Track(2000, fps)
    frames = [f for f in range(3 * track_capacity(CONTRACT, fps)) if f % 37 != 5]  # gaps bridged
    for frame in frames:
        small.push(frame, seen(frame))
        large.push(frame, seen(frame))
        a, b = small.window(CONTRACT), large.window(CONTRACT)
        for x, y in zip(
            (a.poses, a.keypoints_2d, a.visibility, a.fps),
            (b.poses, b.keypoints_2d, b.visibility, b.fps),
            strict=True,
        ):
            np.testing.assert_array_equal(x, y)
    assert small.nbytes == track_bytes(track_capacity(CONTRACT, fps)) < large.nbytes


def test_the_budget_counts_each_tracks_own_bytes() -> None:
    budget = TrackBudget(limit=10)
    table = TrackTable(CONTRACT, per_stream=4, idle_s=10.0, budget=budget)
    table.get("a", 30.0, "pose")
    table.get("b", 240.0, "pose")
    assert budget.bytes == track_bytes(49) + track_bytes(385)
    table.get("a", 60.0, "pose")  # a new rate restarts the track, with the ring of that rate
    assert table.tracks["a"].capacity == 97 and budget.open == 2
    assert budget.bytes == track_bytes(97) + track_bytes(385)
    table.close()
    assert budget.open == 0 and budget.bytes == 0


def test_the_budget_refuses_a_track_past_its_bytes_whatever_its_count() -> None:
    """REPNET_TRACK_MEMORY_MB: tracks at 240 fps hold 8x a 30 fps track's state, so a count alone
    does not bound memory (issue 30: 4,096 tracks at 240 fps held 644 MB)."""
    budget = TrackBudget(limit=100, max_bytes=2 * track_bytes(385) + track_bytes(49))
    table = TrackTable(CONTRACT, per_stream=100, idle_s=10.0, budget=budget)
    table.get("a", 240.0, "pose")
    table.get("b", 240.0, "pose")
    with pytest.raises(TrackLimitReached) as refused:
        table.get("c", 240.0, "people[2].track_id")
    (violation,) = refused.value.violations
    assert violation.field == "people[2].track_id" and "REPNET_TRACK_MEMORY_MB" in violation.reason
    table.get("c", 30.0, "pose")  # a smaller window still fits
    assert budget.open == 3 and budget.bytes <= budget.max_bytes
    table.close()
    assert budget.bytes == 0


def reference_offline(frames: list[int], fps: float, contract: Contract) -> tuple[list[np.ndarray], ...]:
    """Each frame's offline window built the long way: the whole bridged clip of its segment in a
    Track as large as the clip, then the frames around it, the clip's ends repeated."""
    windows: list[list[np.ndarray]] = [[], [], []]
    bones: list[np.ndarray] = []
    q = contract.thinning(fps)
    half = contract.slots(fps / q) // 2
    cuts = [0] + [k for k in range(1, len(frames)) if frames[k] - frames[k - 1] - 1 > round(0.5 * fps)]
    for start, stop in zip(cuts, [*cuts[1:], len(frames)], strict=True):
        part = frames[start:stop]
        clip = Track(part[-1] - part[0] + 1, fps)
        where = []
        for frame in part:
            clip.push(frame, seen(frame))
            where.append(clip.stored - 1)
        for w in where:
            index = np.clip(w + q * np.arange(-half, half + 1), 0, clip.stored - 1)
            for out, array in zip(windows, (clip.poses, clip.keypoints, clip.visibility), strict=True):
                out.append(array[index])
            bones.append(clip.bone_reference())
    return (*(np.stack(w) for w in windows), np.stack(bones))


def request_of(frames: list[int], fps: float, contract: Contract) -> tuple[np.ndarray, ...]:
    """Each frame's window and bone lengths as a temporal request builds them (one track)."""
    poses, points, visibility = (
        np.stack([getattr(seen(f), n) for f in frames]) for n in ("pose", "keypoints", "visibility")
    )
    windows, bones = clip_windows(
        ["a"] * len(frames), np.array(frames), fps, contract, poses, points, visibility
    )
    built = windows.build()
    return built.poses, built.keypoints_2d, built.visibility, bones


GAPPY = [f for f in range(400) if f % 37 not in (5, 6, 7)] + [600, 601, 640, 700, 5000]  # gaps, restarts


@pytest.mark.parametrize("fps", [25.0, 30.0, 90.0, 240.0])
def test_a_causal_request_builds_the_windows_a_stream_track_gives(fps: float) -> None:
    track = Track(track_capacity(CONTRACT, fps), fps)
    expected: list[tuple[np.ndarray, ...]] = []
    for frame in GAPPY:
        track.push(frame, seen(frame))
        w = track.window(CONTRACT)
        expected.append((w.poses[0], w.keypoints_2d[0], w.visibility[0], track.bone_reference()))
    got = request_of(GAPPY, fps, CONTRACT)
    for k, want in enumerate(zip(*expected, strict=True)):  # bit for bit
        np.testing.assert_array_equal(got[k], np.stack(want))


@pytest.mark.parametrize("fps", [25.0, 30.0, 90.0, 240.0])
def test_an_offline_request_builds_the_windows_of_its_whole_bridged_clip(fps: float) -> None:
    offline = Contract("offline", grid_fps=50.0, window=81, max_fps=60.0)
    for got, want in zip(
        request_of(GAPPY, fps, offline), reference_offline(GAPPY, fps, offline), strict=True
    ):
        np.testing.assert_array_equal(got, want)


def test_request_windows_keep_tracks_apart_and_poses_in_request_order() -> None:
    rng = np.random.default_rng(3)
    frames = {"a": GAPPY, "b": list(range(0, 300, 2)), "c": [7]}
    rows = [(t, f) for t, fs in frames.items() for f in fs]
    shuffled = [rows[k] for k in rng.permutation(len(rows))]
    ids, numbers = [t for t, _ in shuffled], np.array([f for _, f in shuffled])
    poses, points, visibility = (
        np.stack([getattr(seen(f), n) for _, f in shuffled]) for n in ("pose", "keypoints", "visibility")
    )
    windows, bones = clip_windows(ids, numbers, 30.0, CONTRACT, poses, points, visibility)
    built = windows.build()
    for track_id, fs in frames.items():
        alone = request_of(fs, 30.0, CONTRACT)
        mine = [k for k, t in enumerate(ids) if t == track_id]
        position = {f: k for k, f in enumerate(fs)}
        order = [position[int(numbers[k])] for k in mine]
        for got, want in zip((built.poses, built.keypoints_2d, built.visibility, bones), alone, strict=True):
            np.testing.assert_array_equal(got[mine], want[order])


def test_a_sparse_clip_costs_its_poses_not_its_span() -> None:
    """300 poses 121 frames apart at 240 fps (each gap bridged: a span of 36,180 frames, whose
    windows once took 1.4 GB) hold 16 bytes per window slot until a batch builds its windows."""
    offline = Contract("offline", grid_fps=50.0, window=81, max_fps=60.0)
    frames = np.arange(0, 300 * 121, 121)
    poses, points, visibility = (np.zeros((300, 17, d), np.float32) for d in (3, 2, 1))
    windows, bones = clip_windows(["a"] * 300, frames, 240.0, offline, poses, points, visibility[..., 0])
    slots = offline.slots(60.0)
    assert len(windows) == 300 and windows.before.shape == (300, slots) == (300, 97)
    assert sum(a.nbytes for a in (windows.before, windows.after, windows.weight)) == 300 * slots * 16
    assert len(windows.slice(0, 64).build()) == 64 and bones.shape == (300, 16)
