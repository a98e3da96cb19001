"""Template alignment, projection, detection mapping and the training and validation sets."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from repnet.core import skeleton
from repnet.train import data, sequences
from tests.training.conftest import STANDING


def _rotation_z(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def test_align_to_template_removes_rotation_scale_and_translation() -> None:
    moved = 1.3 * STANDING @ _rotation_z(1.1).T + [100.0, -50.0, 900.0]
    aligned = data.align_to_template(np.stack([STANDING, moved]))
    np.testing.assert_allclose(aligned[1], aligned[0], atol=1e-2)
    assert np.all(aligned[:, skeleton.ROOT] == 0)
    np.testing.assert_allclose(aligned[0, skeleton.TORSO_JOINTS], skeleton.TEMPLATE_TORSO, atol=25.0)


def test_procrustes_recovers_a_known_similarity() -> None:
    rot = _rotation_z(0.7) @ np.array([[1, 0, 0], [0, 0.6, -0.8], [0, 0.8, 0.6]])
    target = 0.8 * STANDING @ rot.T + [10.0, 20.0, 30.0]
    scale, r, t = data.procrustes(STANDING[None], target[None])
    np.testing.assert_allclose(scale, [0.8], rtol=1e-9)
    np.testing.assert_allclose(r[0], rot, atol=1e-9)
    np.testing.assert_allclose(t[0], [10.0, 20.0, 30.0], atol=1e-6)


def test_hide_random_joints_hides_that_many_non_root_joints_of_every_pose() -> None:
    rng = np.random.default_rng(0)
    points = rng.normal(500.0, 100.0, (200, skeleton.NUM_JOINTS, 2)).astype(np.float32)
    visible = np.ones((200, skeleton.NUM_JOINTS), dtype=np.float32)
    before = points.copy()
    hidden_points, hidden_visible = data.hide_random_joints(points, visible, 3, np.random.default_rng(1))
    assert np.all((hidden_visible == 0).sum(axis=1) == 3)
    assert np.all(hidden_visible[:, skeleton.ROOT] == 1)
    assert np.all(hidden_points[hidden_visible == 0] == 0) and np.all(hidden_points[hidden_visible == 1] != 0)
    np.testing.assert_array_equal(points, before)  # the inputs are left as they were
    assert np.all(visible == 1)
    # Every non-root joint gets hidden somewhere: the draw is not stuck on a few joints.
    non_root = [j for j in range(skeleton.NUM_JOINTS) if j != skeleton.ROOT]
    assert np.all((hidden_visible == 0).any(axis=0)[non_root])
    again, _ = data.hide_random_joints(points, visible, 3, np.random.default_rng(1))
    np.testing.assert_array_equal(again, hidden_points)  # one fixed draw per seed


def test_mpii_detections_map_to_h36m_slots_with_spine_masked() -> None:
    mpii = np.arange(32, dtype=np.float32).reshape(1, 16, 2)
    points, visible = data.mpii_to_h36m(mpii)
    assert visible[0].tolist() == [1.0] * 7 + [0.0] + [1.0] * 9
    assert points[0, 0].tolist() == mpii[0, 6].tolist()  # pelvis
    assert points[0, 16].tolist() == mpii[0, 10].tolist()  # right wrist
    assert points[0, 7].tolist() == [0.0, 0.0]


def test_projection_without_distortion_is_pinhole(synthetic_h36m: Path) -> None:
    cam = data.load_cameras(synthetic_h36m)["S1"]["54138969"]
    world = data.load_poses(synthetic_h36m, "train")["S1/Walking"][:3]
    x_cam = data.world_to_camera(world, cam)
    expected = x_cam[..., :2] / x_cam[..., 2:] * cam.f + cam.c
    np.testing.assert_allclose(data.project_to_pixels(world, cam), expected, rtol=1e-5)


def test_training_sets_hold_out_the_tail_of_each_sequence(synthetic_h36m: Path) -> None:
    train, val = data.build_training_sets(synthetic_h36m, "gt+sh", val_fraction=0.25)
    assert train.poses_aligned.shape == (5 * 90, 17, 3)
    assert train.points_2d.shape == (2 * 4 * 5 * 90, 17, 2)
    assert set(val) == {"gt", "sh"}
    assert val["gt"].poses_camera.shape == (4 * 5 * 30, 17, 3)
    assert np.all(val["sh"].visible[:, skeleton.SPINE] == 0)


def test_excluded_actions_reach_no_pool_no_validation_set_and_no_detector_error(
    synthetic_h36m: Path, sitting_h36m: Path
) -> None:
    """sitting_h36m is synthetic_h36m with sitting sequences: without them, every array is the same."""
    kept, kept_val = data.build_training_sets(sitting_h36m, "gt+sh", exclude_actions="Sitting, SittingDown")
    plain, plain_val = data.build_training_sets(synthetic_h36m, "gt+sh")
    for name in ("poses_aligned", "poses_world", "points_2d", "visible"):
        np.testing.assert_array_equal(getattr(kept, name), getattr(plain, name))
    assert set(kept_val) == set(plain_val)
    for kind, val in plain_val.items():
        np.testing.assert_array_equal(kept_val[kind].poses_camera, val.poses_camera)
        np.testing.assert_array_equal(kept_val[kind].points_2d, val.points_2d)
    errors = sequences.residuals(sitting_h36m, 0.1, "Sitting,SittingDown").streams
    assert [e.tolist() for e, _ in errors] == [
        e.tolist() for e, _ in sequences.residuals(synthetic_h36m).streams
    ]
    every, _ = data.build_training_sets(sitting_h36m, "gt+sh")  # the sitting poses are there to leave out
    assert len(every.poses_aligned) > len(kept.poses_aligned)


def test_an_action_the_data_lacks_is_refused_not_ignored(sitting_h36m: Path) -> None:
    with pytest.raises(ValueError, match="expected actions among Sitting, SittingDown, Walking, got Siting"):
        data.build_training_sets(sitting_h36m, "gt", exclude_actions="Siting")
    assert data.action_name("SittingDown 1") == "SittingDown"


def test_missing_data_dir_names_the_flag_and_variable(tmp_path: Path) -> None:
    with pytest.raises(data.DataNotFound, match="REPNET_H36M_DIR"):
        data.resolve_data_dir(tmp_path)


def test_missing_default_folder_is_named_once(monkeypatch: pytest.MonkeyPatch) -> None:
    # From the repository root, ../shared/data/h36m by the code's place and by the working
    # directory are the same folder: the message names it once.
    monkeypatch.delenv(data.DATA_ENV, raising=False)
    repo = Path(data.__file__).resolve().parent.parent
    monkeypatch.chdir(repo)
    monkeypatch.setattr(Path, "is_file", lambda self: False)
    with pytest.raises(data.DataNotFound) as err:
        data.resolve_data_dir()
    message = str(err.value)
    assert message.count("shared/data/h36m") == 1, message
