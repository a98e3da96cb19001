"""Known values for the camera quantities derived from K and the reprojection into pixels."""

from __future__ import annotations

import numpy as np
import pytest

from repnet.core import geometry
from tests.conftest import POSE_3D


def rotation_about(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues: the (3, 3) rotation by `angle` radians about `axis`."""
    k = axis / np.linalg.norm(axis)
    cross = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.asarray(np.eye(3) + np.sin(angle) * cross + (1 - np.cos(angle)) * cross @ cross)


ROTATION = rotation_about(np.array([0.3, 1.0, -0.2]), 0.7)


def test_scale_and_rotation_of_a_scaled_rotation() -> None:
    camera = (0.004 * ROTATION[:2])[None]
    assert geometry.camera_scale(camera)[0] == np.float32(0.004)
    np.testing.assert_allclose(geometry.camera_rotation(camera)[0], ROTATION, atol=1e-6)


def test_rotation_is_orthonormal_with_det_one_for_any_camera() -> None:
    cameras = np.random.default_rng(0).normal(size=(64, 2, 3))
    cameras[0, 1] = 2 * cameras[0, 0]  # rows parallel: still a rotation
    cameras[1] = 0  # a zero camera: still a rotation
    rotations = geometry.camera_rotation(cameras).astype(np.float64)
    np.testing.assert_allclose(
        rotations @ rotations.transpose(0, 2, 1), np.broadcast_to(np.eye(3), (64, 3, 3)), atol=1e-5
    )
    np.testing.assert_allclose(np.linalg.det(rotations), 1.0, atol=1e-5)


def test_rotate_to_camera_applies_r() -> None:
    rotated = geometry.rotate_to_camera(POSE_3D[None], ROTATION[None])[0]
    np.testing.assert_allclose(rotated, POSE_3D @ ROTATION.T, atol=1e-3)
    np.testing.assert_allclose(np.linalg.norm(rotated, axis=1), np.linalg.norm(POSE_3D, axis=1), rtol=1e-6)


def test_reprojection_recovers_an_exact_weak_perspective_input() -> None:
    camera = 0.004 * ROTATION[:2]
    kx = POSE_3D @ camera.T
    camera = camera / np.sqrt(((kx - kx.mean(0)) ** 2).sum() / (2 * 17))  # K X now has std 1
    pixels = 230.0 * (POSE_3D @ camera.T) + [640.0, 360.0]  # the input: K X up to scale and shift
    visible = np.ones((1, 17), bool)
    reprojection = geometry.reproject(camera[None], POSE_3D[None], pixels[None], visible)
    np.testing.assert_allclose(reprojection[0], pixels, atol=1e-3)
    assert geometry.reprojection_error(reprojection, pixels[None], visible)[0] < 1e-3


def test_invisible_joints_do_not_move_the_reprojection() -> None:
    camera = (0.004 * ROTATION[:2])[None]
    pixels = np.random.default_rng(1).uniform(0, 1000, (1, 17, 2))
    visible = np.ones((1, 17), bool)
    visible[0, [4, 9]] = False
    poisoned = pixels.copy()
    poisoned[0, [4, 9]] = [np.nan, 1e30]
    a = geometry.reproject(camera, POSE_3D[None], pixels, visible)
    b = geometry.reproject(camera, POSE_3D[None], poisoned, visible)
    np.testing.assert_array_equal(a, b)
    assert np.isfinite(geometry.reprojection_error(b, poisoned, visible)).all()


def test_rotation_rows_are_the_polar_factor_of_the_camera() -> None:
    """The closed form equals U V^T of K's SVD, the nearest row-orthonormal matrix; cameras of
    rank 1 or 0 (where that matrix is not unique) still give a rotation."""
    rng = np.random.default_rng(7)
    camera = rng.normal(size=(200, 2, 3)) * rng.uniform(1e-4, 10, (200, 1, 1))
    camera[0, 1] = 3 * camera[0, 0]  # rank 1
    camera[1] = 0.0
    u, _, vt = np.linalg.svd(camera, full_matrices=False)
    rotation = geometry.camera_rotation(camera.astype(np.float32))
    np.testing.assert_allclose(rotation[2:, :2], (u @ vt)[2:], atol=1e-5)
    rotation64 = rotation.astype(np.float64)
    np.testing.assert_allclose(
        rotation64 @ rotation64.transpose(0, 2, 1), np.broadcast_to(np.eye(3), (200, 3, 3)), atol=1e-5
    )
    np.testing.assert_allclose(np.linalg.det(rotation64), 1.0, atol=1e-5)


def test_ray_rotation_turns_the_optical_axis_onto_the_ray_through_the_centroid() -> None:
    points = np.array(
        [[[600.0, 400.0], [700.0, 500.0], [1e6, -1e6]], [[500.0, 500.0], [500.0, 500.0], [0, 0]]]
    )
    visible = np.array([[True, True, False], [True, True, False]])
    focal, centre = np.full((2, 2), 1000.0), np.full((2, 2), 500.0)
    turn = geometry.ray_rotation(points, visible, focal, centre).astype(np.float64)
    ray = np.array([0.15, -0.05, 1.0]) / np.linalg.norm([0.15, -0.05, 1.0])
    np.testing.assert_allclose(turn[0] @ [0.0, 0.0, 1.0], ray, atol=1e-6)
    np.testing.assert_allclose(turn[1], np.eye(3), atol=1e-7)  # a person on the axis: no turn
    np.testing.assert_allclose(turn[0] @ turn[0].T, np.eye(3), atol=1e-6)
    assert np.linalg.det(turn[0]) == pytest.approx(1.0, abs=1e-6)
    # The smallest turn: the direction perpendicular to the axis and the ray stays put.
    axis = np.cross([0.0, 0.0, 1.0], ray)
    np.testing.assert_allclose(turn[0] @ axis, axis, atol=1e-6)
