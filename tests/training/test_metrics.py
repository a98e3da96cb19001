"""Known-value tests for repnet.train.metrics: MPJPE, Procrustes, PCK, AUC, symmetry, camera rotation."""

from __future__ import annotations

import numpy as np
import pytest

from repnet.core import geometry, skeleton
from repnet.train import metrics
from repnet.train.data import procrustes


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues: (3,) axis, radians -> (3, 3) proper rotation."""
    k = axis / np.linalg.norm(axis)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * kx + (1 - np.cos(angle)) * kx @ kx


def _pose() -> np.ndarray:
    """(1, 17, 3) left/right symmetric standing pose, mm, pelvis at the origin, y down."""
    half = {"hip": 130.0, "knee": 120.0, "ankle": 120.0, "shoulder": 150.0, "elbow": 180.0, "wrist": 190.0}
    p = np.zeros((17, 3))
    for side, sign in (("right", -1.0), ("left", 1.0)):
        hip, knee, ankle = (skeleton.JOINT_NAMES.index(f"{side}_{j}") for j in ("hip", "knee", "ankle"))
        sh, el, wr = (skeleton.JOINT_NAMES.index(f"{side}_{j}") for j in ("shoulder", "elbow", "wrist"))
        p[hip] = [sign * half["hip"], 0, 0]
        p[knee] = [sign * half["knee"], 450, 20]
        p[ankle] = [sign * half["ankle"], 880, 0]
        p[sh] = [sign * half["shoulder"], -450, 0]
        p[el] = [sign * half["elbow"], -180, 40]
        p[wr] = [sign * half["wrist"], 60, 80]
    p[7], p[8], p[9], p[10] = [0, -230, 10], [0, -470, 0], [0, -560, -40], [0, -680, 0]
    return p[None]


def test_mpjpe_of_one_displaced_joint_is_its_share():
    gt = _pose()
    pred = gt.copy()
    pred[0, 13, 0] += 17.0  # left wrist 17 mm off: mean over 17 joints is 1 mm
    assert metrics.mpjpe(pred, gt) == pytest.approx(1.0)
    np.testing.assert_allclose(metrics.joint_errors(pred, gt)[0, 13], 17.0)


def test_mpjpe_ignores_global_translation_but_not_root_offset():
    gt = _pose()
    assert metrics.mpjpe(gt + np.array([100.0, -50.0, 3000.0]), gt) == pytest.approx(0.0, abs=1e-9)
    pred = gt.copy()
    pred[0, skeleton.ROOT] += [0.0, 34.0, 0.0]  # root moved: after root alignment 16 joints are 34 mm off
    assert metrics.mpjpe(pred, gt) == pytest.approx(34.0 * 16 / 17)


def test_procrustes_recovers_a_known_similarity():
    rng = np.random.default_rng(0)
    gt = _pose() + rng.normal(0.0, 30.0, (1, 17, 3))
    rot = _rotation(np.array([0.3, -1.0, 0.5]), 1.1)
    pred = 0.7 * gt @ rot.T + np.array([10.0, -200.0, 4000.0])
    assert metrics.mpjpe(pred, gt) > 50.0
    assert metrics.pa_mpjpe(pred, gt) == pytest.approx(0.0, abs=1e-6)
    scale, r, _ = procrustes(pred, gt)
    assert scale[0] == pytest.approx(1 / 0.7)
    np.testing.assert_allclose(r[0], rot.T, atol=1e-9)


def test_procrustes_does_not_undo_a_change_of_shape():
    gt = _pose()
    pred = gt.copy()
    pred[0, 16] += [0.0, 0.0, 200.0]  # right wrist pushed back 20 cm
    assert metrics.mpjpe(pred, gt) == pytest.approx(200 / 17)
    # the alignment minimises the squared error (it spreads the wrist's 200 mm over all joints)
    aligned = metrics.procrustes_errors(pred, gt)
    assert (aligned**2).sum() < 200.0**2
    assert metrics.pa_mpjpe(pred, gt) > 5.0


def test_pck_counts_errors_within_the_threshold():
    errors = np.array([[0.0, 100.0, 149.9, 150.0, 200.0]])
    assert metrics.pck(errors) == pytest.approx(80.0)
    assert metrics.pck(errors, threshold=100.0) == pytest.approx(40.0)


def test_auc_of_constant_errors_is_the_share_of_thresholds_above_them():
    errors = np.full((10, 17), 75.0)
    # thresholds 0, 5, ..., 150: 16 of the 31 (75..150) reach 75 mm
    assert metrics.auc(errors) == pytest.approx(100.0 * 16 / 31)
    assert metrics.auc(np.full((1, 17), 500.0)) == 0.0
    assert metrics.auc(np.zeros((1, 17))) == 100.0


def test_symmetry_error_of_a_symmetric_pose_is_zero():
    assert metrics.symmetry_error(_pose())[0] == pytest.approx(0.0, abs=1e-9)


def test_symmetry_error_sums_left_right_bone_differences():
    pose = _pose()
    forearm = pose[0, 13] - pose[0, 12]
    pose[0, 13] += 30.0 * forearm / np.linalg.norm(forearm)  # left forearm 30 mm longer
    shin = pose[0, 3] - pose[0, 2]
    pose[0, 3] -= 10.0 * shin / np.linalg.norm(shin)  # right shin 10 mm shorter
    assert metrics.symmetry_error(pose)[0] == pytest.approx(40.0)


def test_rotation_from_camera_recovers_a_known_rotation():
    rot = np.stack([_rotation(np.array([1.0, 2.0, -0.5]), 0.8), _rotation(np.array([0.0, 1.0, 0.0]), -2.5)])
    camera = np.array([0.004, 2.5])[:, None, None] * rot[:, :2]  # K = s R[:2]
    recovered = geometry.rotation_of_camera(camera)
    np.testing.assert_allclose(recovered, rot, atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(recovered), 1.0)


def test_rotation_from_camera_is_proper_for_a_skewed_camera():
    rng = np.random.default_rng(1)
    recovered = geometry.rotation_of_camera(rng.normal(size=(50, 2, 3)))
    np.testing.assert_allclose(
        recovered @ recovered.transpose(0, 2, 1), np.broadcast_to(np.eye(3), (50, 3, 3)), atol=1e-9
    )
    np.testing.assert_allclose(np.linalg.det(recovered), 1.0)


def test_to_camera_frame_undoes_the_camera_rotation():
    gt_cam = _pose()
    rot = _rotation(np.array([0.2, 1.0, 0.1]), 2.0)
    template = gt_cam @ rot  # the model's template-frame pose, seen by a camera rotated by rot
    camera = 0.01 * rot[None, :2]
    np.testing.assert_allclose(metrics.to_camera_frame(template, camera), gt_cam, atol=1e-9)
    assert metrics.mpjpe(metrics.to_camera_frame(template, camera), gt_cam) == pytest.approx(0.0, abs=1e-9)


def test_summarize_reports_means_medians_and_symmetry():
    p1 = np.array([[10.0] * 17, [30.0] * 17, [200.0] * 17])
    p2 = p1 / 2
    sym = np.array([1.0, 2.0, 6.0])
    figures = metrics.summarize(p1, p2, sym, np.zeros(3))
    assert figures["poses"] == 3
    assert figures["mpjpe"] == pytest.approx(80.0)
    assert figures["mpjpe_median"] == pytest.approx(30.0)
    assert figures["pa_mpjpe"] == pytest.approx(40.0)
    assert figures["pck3d_150"] == pytest.approx(100 * 2 / 3)
    assert figures["pa_pck3d_150"] == pytest.approx(100.0)
    assert (figures["symmetry_mean"], figures["symmetry_max"]) == (pytest.approx(3.0), 6.0)
    assert figures["symmetry_std"] == pytest.approx(np.std([1.0, 2.0, 6.0]))
    assert figures["gt_symmetry_mean"] == 0.0


def test_rotation_to_ray_turns_the_optical_axis_onto_the_ray() -> None:
    direction = np.array([[0.0, 0.0, 2.0], [0.3, -0.2, 1.0], [-1.0, 0.5, 1.5]])
    rot = geometry.rotation_to_ray(direction)
    np.testing.assert_allclose(rot[0], np.eye(3), atol=1e-12)
    unit = direction / np.linalg.norm(direction, axis=1, keepdims=True)
    np.testing.assert_allclose(rot @ np.array([0.0, 0.0, 1.0]), unit, atol=1e-12)
    np.testing.assert_allclose(rot @ rot.transpose(0, 2, 1), np.eye(3)[None].repeat(3, 0), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(rot), 1.0, atol=1e-12)
    # The smallest rotation: a vector perpendicular to both the axis and the ray stays put.
    axis = np.cross([0.0, 0.0, 1.0], unit[1])
    np.testing.assert_allclose(rot[1] @ axis, axis, atol=1e-12)


def test_ray_rotation_goes_through_the_centroid_of_the_visible_joints() -> None:
    points = np.array([[[600.0, 400.0], [700.0, 500.0], [1e6, 1e6]]])
    visible = np.array([[1.0, 1.0, 0.0]])
    rot = geometry.ray_turn(points, visible, np.array([[1000.0, 1000.0]]), np.array([[500.0, 500.0]]))
    expected = np.array([0.15, -0.05, 1.0]) / np.linalg.norm([0.15, -0.05, 1.0])
    np.testing.assert_allclose(rot[0] @ np.array([0.0, 0.0, 1.0]), expected, atol=1e-12)


def test_off_axis_errors_are_the_chords_of_the_turn_onto_the_ray() -> None:
    """A joint r mm from the pelvis moves 2 r sin(a / 2) when the pose turns by a onto the ray."""
    angle = np.radians(10.0)
    ray = geometry.rotation_to_ray(np.array([[np.sin(angle), 0.0, np.cos(angle)], [0.0, 0.0, 1.0]]))
    gt = np.repeat(_pose(), 2, axis=0) + 500.0  # anywhere: the root is aligned first
    errors, angles = metrics.off_axis_errors(gt, ray)
    np.testing.assert_allclose(angles, [10.0, 0.0], atol=1e-9)
    # The turn is about the camera's y axis: a joint's distance from that axis through the root.
    rooted = metrics.root_align(gt)[0]
    radius = np.linalg.norm(rooted[:, [0, 2]], axis=1)
    np.testing.assert_allclose(errors[0], 2.0 * radius * np.sin(angle / 2.0), atol=1e-9)
    np.testing.assert_allclose(errors[1], 0.0, atol=1e-12)


def test_spearman_ranks_ties_by_their_mean_and_ignores_the_scale() -> None:
    np.testing.assert_array_equal(metrics.average_ranks(np.array([10.0, 30.0, 20.0, 20.0])), [1, 4, 2.5, 2.5])
    x = np.array([1.0, 2.0, 3.0, 4.0, 5.0])
    assert metrics.spearman(x, np.exp(x)) == pytest.approx(1.0)
    assert metrics.spearman(x, -(x**3)) == pytest.approx(-1.0)
    # ranks (1, 2, 3, 4) and (1.5, 1.5, 4, 3): Pearson of the centred ranks = 3.5 / sqrt(5 * 4.5)
    tied = metrics.spearman(np.arange(4.0), np.array([0.0, 0.0, 9.0, 5.0]))
    assert tied == pytest.approx(3.5 / np.sqrt(22.5))
    assert metrics.spearman(x, np.ones(5)) == 0.0
