"""Tracks without a server: a track's ring is sized for its own frame rate and gives the same
windows as a larger one; the table's budget counts each track's bytes."""

from __future__ import annotations

import numpy as np
import pytest

from service.temporal import Contract
from service.tracks import Observation, Track, TrackBudget, TrackTable, track_bytes, track_capacity

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
