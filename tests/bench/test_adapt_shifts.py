"""bench.adapt_shifts: the 2D a built shift gives `repnet adapt`, as every k-th frame or as clips."""

from __future__ import annotations

import numpy as np

from bench import adapt_shifts
from repnet.train import data, synthetic


def _poses() -> dict[str, np.ndarray]:
    """Two source sequences and one of a subject the shifts never take, world poses (mm, Z up)
    whose pelvis walks along X by 10 mm a frame and whose joints hold their frame number in Y."""
    rng = np.random.default_rng(0)
    out = {}
    for key, frames in (("S1/Walking", 400), ("S5/Eating", 300), ("S9/Walking", 200)):
        pose = rng.normal(0.0, 200.0, (1, 17, 3)) + np.array([0.0, 0.0, 900.0])
        seq = np.repeat(pose, frames, axis=0)
        seq[:, :, 0] += 10.0 * np.arange(frames)[:, None]
        seq[:, 1:, 1] += np.arange(frames)[:, None]
        out[key] = seq
    return out


def test_every_kth_frame_is_the_stride_over_the_source_heads_in_a_row() -> None:
    poses = _poses()
    world, _ = adapt_shifts.source_runs(poses, 100, 1)
    heads = [poses[k][: data.sequence_split(len(poses[k]), 0.1)] for k in ("S1/Walking", "S5/Eating")]
    expected = np.concatenate(heads)[:: len(np.concatenate(heads)) // 100]
    np.testing.assert_array_equal(world, expected - expected[:, :1])


def test_clips_are_runs_of_consecutive_frames_within_one_sequence_each_seen_by_one_camera() -> None:
    poses = _poses()
    world, frames = adapt_shifts.source_runs(poses, 100, 8)
    runs = frames.reshape(-1, 8)
    assert (np.diff(runs, axis=1) == 1).all()  # consecutive within a run
    assert (np.diff(runs[:, 0]) > 8).all()  # and apart from the next one
    # Within a run the joints' frame number (Y above the pelvis) steps by one: frames of one sequence.
    assert np.allclose(np.diff(world[:, 1, 1].reshape(-1, 8), axis=1), 1.0)
    still = np.repeat(world[:1], len(world), axis=0)
    pixels = adapt_shifts.clip_views(still, frames, 8, seed=1, elevation=synthetic.ELEVATION_DEG)
    by_run = pixels.reshape(-1, 8, 17, 2)
    within = np.abs(by_run - by_run[:, :1]).max(axis=(1, 2, 3))
    between = np.abs(by_run[1:, 0] - by_run[:-1, 0]).max(axis=(1, 2))
    assert within.max() < 20.0 < between.min()  # the 2 px noise only, against another camera
