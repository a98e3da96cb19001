"""The tracker of files of detections: people followed by their nearest pose, with a gate and gaps."""

from __future__ import annotations

import numpy as np

from repnet.client.tracker import GATE, assign_tracks, costs, match
from tests.conftest import POSE_3D, project


def person(yaw: float, shift_x: float = 0.0, shift_y: float = 0.0) -> np.ndarray:
    """(17, 2) px: the tests' person turned by yaw, moved in the image."""
    return project(POSE_3D, yaw_deg=yaw) + [shift_x, shift_y]


def test_two_people_keep_their_tracks_whatever_order_the_detector_lists_them() -> None:
    frames, points, who = [], [], []
    for f in range(12):
        a, b = person(5.0 * f, 6.0 * f), person(-5.0 * f, 300.0 - 6.0 * f)  # walking towards each other
        pair = [("b", b), ("a", a)] if f % 3 == 1 else [("a", a), ("b", b)]  # the detector's order changes
        for name, pose in pair:
            frames.append(f)
            points.append(pose)
            who.append(name)
    tracks = assign_tracks(np.array(frames), np.stack(points), fps=30.0)
    assert {(name, int(t)) for name, t in zip(who, tracks, strict=True)} == {("a", 0), ("b", 1)}


def test_a_short_gap_keeps_the_track_and_a_long_one_starts_a_new_one() -> None:
    fps = 30.0  # the service bridges 15 missing frames at 30 fps
    frames = np.array([0, 1, 2, 10, 11, 40, 41])  # 7 missing, then 28 missing
    points = np.stack([person(2.0 * f, 1.0 * f) for f in frames])
    assert assign_tracks(frames, points, fps).tolist() == [0, 0, 0, 0, 0, 1, 1]


def test_a_jump_past_the_gate_starts_a_new_track_and_a_newcomer_gets_one() -> None:
    frames = np.array([0, 1, 2, 2, 3])
    points = np.stack([person(0), person(1), person(2, 2000.0), person(2, 0, 5), person(3, 2000.0)])
    tracks = assign_tracks(frames, points, fps=25.0)
    assert tracks.tolist() == [0, 0, 1, 0, 1]  # the far pose of frame 2 is someone else


def test_poses_with_too_few_joints_in_common_are_never_matched() -> None:
    sparse = person(0).copy()
    sparse[4:] = np.nan  # 4 joints, of which 3 after the next frame loses one
    later = sparse.copy()
    later[3] = np.nan
    frames = np.array([0, 1, 2])
    tracks = assign_tracks(frames, np.stack([person(0), sparse, later]), fps=30.0)
    assert tracks.tolist() == [0, 0, 1]  # 4 shared joints match; 3 do not


def test_cost_is_the_mean_joint_distance_in_body_sizes_and_matching_takes_the_cheapest_first() -> None:
    from repnet.client.tracker import _Track

    base = person(0)
    visible = np.ones((2, 17), bool)
    sizes = np.array([100.0, 100.0])
    track = _Track(0, 0, base, np.ones(17, bool), 100.0)
    cost = costs([track], np.stack([base + [30.0, 40.0], base]), visible, sizes)
    np.testing.assert_allclose(cost, [[0.5, 0.0]])  # 50 px over 100 px, and 0
    # the cheapest pair first; a row or column once taken is out
    assert match(np.array([[0.1, 0.4], [0.2, 0.3]]), np.full((2, 2), True)) == [(0, 0), (1, 1)]
    assert match(np.array([[0.3, 0.1], [0.2, 0.4]]), np.full((2, 2), True)) == [(0, 1), (1, 0)]
    assert match(np.array([[GATE * 3]]), np.array([[False]])) == []
