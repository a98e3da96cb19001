"""Which poses of an input are consecutive frames of one person (core.links, Poses.previous_frames),
and an NPZ's own frame numbers."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from repnet.core.links import kept_links, previous_frames, shifted
from repnet.io.pose_file import load_poses
from repnet.io.poses import InputFileError, Poses


def _poses(frames: list[int], people: list[int], **given: object) -> Poses:
    n = len(frames)
    points = np.zeros((n, 17, 2))
    return replace(Poses(points, None, None, np.array(frames), np.array(people)), **given)  # type: ignore[arg-type]


def test_each_pose_links_to_the_same_person_one_frame_before() -> None:
    links = previous_frames([0, 1, 1, 2, 4, 5], ["a", "a", "b", "b", "a", None])
    # a@1 <- a@0; b@1 has no b@0; b@2 <- b@1; a@4 has no a@3 (a gap); an unknown person links nothing
    assert links.tolist() == [-1, 0, -1, 2, -1, -1]


def test_kept_links_are_renumbered_and_cut_where_a_pose_was_skipped() -> None:
    previous = np.array([-1, 0, 1, 2, 3])
    kept = np.array([True, True, False, True, True])
    assert kept_links(previous, kept).tolist() == [-1, 0, -1, 2]
    assert shifted(np.array([-1, 0, 1]), 10).tolist() == [-1, 10, 11]


def test_a_clip_of_one_pose_a_frame_is_one_person() -> None:
    assert _poses([0, 1, 2, 5], [0, 0, 0, 0]).previous_frames().tolist() == [-1, 0, 1, -1]


def test_frames_of_several_people_link_by_their_tracks_or_not_at_all() -> None:
    crowd = _poses([0, 0, 1, 1], [0, 1, 0, 1])
    assert crowd.previous_frames().tolist() == [-1, -1, -1, -1]  # who is who is not known
    tracked = replace(crowd, track_id=("x", "y", "y", "x"))
    assert tracked.previous_frames().tolist() == [-1, -1, 1, 0]


def test_unrelated_images_link_nothing() -> None:
    images = _poses([7, 8, 9], [0, 0, 0], numbered_by="image ids")
    assert images.previous_frames().tolist() == [-1, -1, -1]


def test_an_npz_gives_its_poses_frame_numbers(tmp_path: Path) -> None:
    keypoints = np.random.default_rng(0).uniform(100, 900, (5, 17, 2))
    np.savez(path := tmp_path / "clip.npz", keypoints=keypoints, frame=np.array([3, 4, 5, 9, 10]))
    poses = load_poses(path)
    assert poses.frame.tolist() == [3, 4, 5, 9, 10]
    assert poses.previous_frames().tolist() == [-1, 0, 1, -1, 3]
    np.savez(plain := tmp_path / "plain.npz", keypoints=keypoints)
    assert load_poses(plain).previous_frames().tolist() == [-1, 0, 1, 2, 3]  # one person's frames in order


@pytest.mark.parametrize(
    ("frame", "said"),
    [
        (np.array([0.0, 1.0]), "'frame' must be (2,) integers"),
        (np.array([0, 1, 2]), "'frame' must be (2,) integers"),
        (np.array([-1, 0]), "'frame' numbers must be 0..9007199254740991, got -1..0"),
    ],
)
def test_a_bad_npz_frame_array_is_named(tmp_path: Path, frame: np.ndarray, said: str) -> None:
    np.savez(path := tmp_path / "bad.npz", keypoints=np.ones((2, 17, 2)), frame=frame)
    with pytest.raises(InputFileError) as err:
        load_poses(path)
    assert said in str(err.value)
