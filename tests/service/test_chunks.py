"""Cutting a clip into requests: within the limit, each pose answered once, each cut track sent with
the frames its windows read; and the contract's reach is what the service's windows read."""

from __future__ import annotations

import numpy as np
import pytest

from repnet.client.chunks import Part, assemble, batches, split_clip
from repnet.core.contract import Contract
from repnet.runtime.tracks import Observation, Track, clip_windows, track_capacity

CAUSAL = Contract("causal", grid_fps=50.0, window=81, max_fps=60.0)
OFFLINE = Contract("offline", grid_fps=50.0, window=81, max_fps=60.0)


def numbered(frames: np.ndarray) -> list[Observation]:
    """Observations whose keypoint x is their frame number, so a window shows which frames it read."""
    return [
        Observation(
            np.zeros((17, 3), np.float32), np.full((17, 2), float(f), np.float32), np.ones(17, np.float32)
        )
        for f in frames
    ]


def request_windows(
    frames: np.ndarray,
    seen: list[Observation],
    fps: float,
    contract: Contract,
    track_ids: list[str] | None = None,
) -> np.ndarray:
    """(M, K, J, 2) the keypoints of each pose's window as a temporal request builds them."""
    ids = track_ids or ["a"] * len(frames)
    arrays = (np.stack([getattr(o, name) for o in seen]) for name in ("pose", "keypoints", "visibility"))
    windows, _ = clip_windows(ids, frames, fps, contract, *arrays)
    return windows.build().keypoints_2d


@pytest.mark.parametrize("fps", [25.0, 30.0, 50.0, 60.0, 100.0, 240.0])
def test_reach_is_how_far_the_services_windows_read(fps: float) -> None:
    frames = np.arange(400)
    seen = numbered(frames)
    read = request_windows(frames, seen, fps, OFFLINE)[200, :, 0, 0]  # the window of frame 200
    assert (200 - read.min(), read.max() - 200) == OFFLINE.reach(fps)
    track = Track(track_capacity(CAUSAL, fps), fps)
    for frame, observation in zip(frames.tolist(), seen, strict=True):
        track.push(frame, observation)
    window = track.window(CAUSAL).keypoints_2d[0, :, 0, 0]  # the newest frame's: 399
    assert (399 - window.min(), window.max() - 399) == CAUSAL.reach(fps)


def reads(frames: np.ndarray, kept: int, reach: tuple[int, int]) -> set[int]:
    """The positions whose poses the window of pose `kept` of one track reads, with the pose beyond
    each edge (a bridged gap there is filled from it)."""
    low, high = frames[kept] - reach[0], frames[kept] + reach[1]
    inside = set(np.flatnonzero((frames >= low) & (frames <= high)).tolist())
    below, above = np.flatnonzero(frames < low), np.flatnonzero(frames > high)
    if len(below) and not (frames == low).any():
        inside.add(int(below[-1]))
    if len(above) and not (frames == high).any():
        inside.add(int(above[0]))
    return inside


@pytest.mark.parametrize("reach", [(48, 0), (24, 24)], ids=["causal", "offline"])
def test_every_pose_is_kept_once_in_a_request_that_holds_what_its_window_reads(
    reach: tuple[int, int],
) -> None:
    rng = np.random.default_rng(1)
    a = np.sort(rng.choice(400, 300, replace=False))  # a long track with gaps
    b = np.arange(30)  # a short one
    track_ids = [*["a"] * len(a), None, *["b"] * len(b)]
    frames = np.concatenate([a, [0], b])
    parts = split_clip(track_ids, frames, reach, max_poses=100)
    assert all(len(p) <= 100 for p in parts)
    kept = np.concatenate([p.send[p.keep] for p in parts])
    assert sorted(kept.tolist()) == list(range(len(frames)))
    for part in parts:
        assert (np.diff(part.send) > 0).all()  # request order is clip order
        sent = set(part.send.tolist())
        for k in part.send[part.keep & (part.send < len(a))].tolist():
            assert reads(a, k, reach) <= sent, k
    whole = [p for p in parts if set(range(len(a) + 1, len(frames))) <= set(p.send.tolist())]
    assert len(whole) == 1  # a track that fits in a request is never cut


def test_a_request_too_small_for_one_frames_context_is_refused() -> None:
    with pytest.raises(ValueError, match="cannot hold one frame's context"):
        split_clip(["a"] * 100, np.arange(100), (48, 0), max_poses=40)
    parts = split_clip(["a"] * 100, np.arange(100), (48, 0), max_poses=50)
    assert [int(p.keep.sum()) for p in parts] == [50] + [2] * 25  # then 48 frames of context each


def test_assemble_puts_the_kept_answers_in_place_and_checks_every_pose_has_one() -> None:
    parts = [
        Part(np.array([0, 1, 2]), np.array([True, True, False])),
        Part(np.array([1, 2]), np.array([False, True])),
    ]
    assert assemble(3, parts, [["a0", "a1", "a2"], ["b1", "b2"]]) == ["a0", "a1", "b2"]
    with pytest.raises(ValueError, match="got no answer"):
        assemble(4, parts, [["a0", "a1", "a2"], ["b1", "b2"]])
    assert [p.send.tolist() for p in batches(5, 2)] == [[0, 1], [2, 3], [4]]


def causal_windows(frames: np.ndarray, seen: list[Observation], fps: float) -> np.ndarray:
    """Each pose's causal window (its keypoints), as a request's track gives them."""
    return request_windows(frames, seen, fps, CAUSAL)


def offline_of(frames: np.ndarray, seen: list[Observation], fps: float) -> np.ndarray:
    """Each pose's offline window (its keypoints), as a request's track gives them."""
    return request_windows(frames, seen, fps, OFFLINE)


@pytest.mark.parametrize("mode", ["causal", "offline"])
@pytest.mark.parametrize("step", [0, 5], ids=["random-gaps", "every-5th"])
def test_windows_of_a_cut_track_equal_those_of_the_whole(mode: str, step: int) -> None:
    """The windows a part's request builds for its kept poses are those of the whole clip: with
    random gaps, and with every 5th frame (4 bridged between each two: a part's edge always in a gap)."""
    rng = np.random.default_rng(2)
    frames = np.arange(0, 5 * 240, 5) if step else np.sort(rng.choice(300, 240, replace=False))
    frames[120:] += 40  # a gap too long to bridge: two segments
    seen = numbered(frames)
    fps = 30.0
    contract, windows = (OFFLINE, offline_of) if mode == "offline" else (CAUSAL, causal_windows)
    expected = windows(frames, seen, fps)
    parts = split_clip(["a"] * len(frames), frames, contract.reach(fps), max_poses=60)
    assert len(parts) >= 4
    for part in parts:
        got = windows(frames[part.send], [seen[k] for k in part.send], fps)
        for k, window, kept in zip(part.send.tolist(), got, part.keep.tolist(), strict=True):
            if kept:
                np.testing.assert_array_equal(window, expected[k])
