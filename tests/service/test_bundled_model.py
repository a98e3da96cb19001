"""The bundled model itself: its plausibility output and how it orders real and broken poses."""

from __future__ import annotations

import json

import numpy as np
import pytest

from service.lifter import Lifter
from tests.conftest import POSE_3D, project, reply_of

# (parent, child) arm and leg bones of the Human3.6M 17-joint skeleton.
LIMBS = {"left forearm": (12, 13), "right forearm": (15, 16), "left shin": (5, 6), "right shin": (2, 3)}
# Views with the limbs across the image: turned further, a 30 % longer limb in 2D can also be the
# real limb turned towards the camera (at 60 degrees one shin of this pose already is).
YAWS_DEG = (-25.0, 0.0, 25.0)


def _stretched(pose: np.ndarray, parent: int, child: int, factor: float) -> np.ndarray:
    """The pose with the bone parent->child (and its end joint) 30 % longer; a limb end has no
    children in this skeleton, so nothing else moves."""
    out = pose.copy()
    out[child] = pose[parent] + factor * (pose[child] - pose[parent])
    return out


@pytest.fixture(scope="module")
def bundled(lifter: Lifter) -> Lifter:
    if not lifter.has_plausibility:
        pytest.skip("the loaded model has no plausibility output")
    return lifter


def test_bundled_model_documents_its_plausibility_calibration(bundled: Lifter) -> None:
    meta = bundled.info.metadata
    calibration = json.loads(meta["plausibility_calibration"])
    table = calibration["critic_scores_at_quantiles"]
    assert len(table) == calibration["levels"] > 100 and table == sorted(table)
    assert "real" in meta["plausibility"]


def test_a_real_pose_is_more_plausible_than_the_same_pose_with_a_limb_stretched_30_percent(
    bundled: Lifter,
) -> None:
    cases = [(name, yaw) for name in LIMBS for yaw in YAWS_DEG]
    real = np.stack([project(POSE_3D, yaw) for _, yaw in cases]).astype(np.float32)
    broken = np.stack([project(_stretched(POSE_3D, *LIMBS[name], 1.3), yaw) for name, yaw in cases]).astype(
        np.float32
    )
    visible = np.ones(real.shape[:2], dtype=bool)
    p_real = bundled.lift(real, visible).plausibility
    p_broken = bundled.lift(broken, visible).plausibility
    assert p_real is not None and p_broken is not None
    assert np.all((p_real >= 0) & (p_real <= 1)) and np.all((p_broken >= 0) & (p_broken <= 1))
    worse = [case for case, r, b in zip(cases, p_real, p_broken, strict=True) if not r > b]
    assert not worse, f"stretched limb not ranked below the real pose for {worse}"


def test_garbage_input_is_flagged_implausible(bundled: Lifter) -> None:
    real = np.stack([project(POSE_3D, yaw) for yaw in YAWS_DEG]).astype(np.float32)
    swapped = real.copy()
    swapped[:, [3, 16]] = real[:, [16, 3]]  # right ankle and right wrist exchanged
    visible = np.ones(real.shape[:2], dtype=bool)
    lifted_real, lifted_swapped = bundled.lift(real, visible), bundled.lift(swapped, visible)
    p_real, p_swapped = lifted_real.plausibility, lifted_swapped.plausibility
    assert p_real is not None and p_swapped is not None
    # repnet-h36m-v2 lifted this input to a wild pose (plausibility 0.0, reprojection error
    # 580-1780 px); v3, v4 and v5 lift it to a body-like pose that cannot fit the input: below most
    # real poses and with several times the reprojection error of the real input.
    assert np.all(p_real > 0.9) and np.all(p_swapped < 0.3)
    error_real = reply_of(bundled, real).columns["reprojection_error_px"]
    error_swapped = reply_of(bundled, swapped).columns["reprojection_error_px"]
    assert np.all(error_swapped > 5 * error_real)


def test_a_mirror_averaged_model_answers_the_mirror_image_with_the_mirrored_pose(bundled: Lifter) -> None:
    if not json.loads(bundled.info.metadata.get("mirror_average", "false")):
        pytest.skip("the loaded model does not average its answers with the mirrored ones")
    names = json.loads(bundled.info.metadata["joint_names"])
    swap = [names.index(n.replace("left", "#").replace("right", "left").replace("#", "right")) for n in names]
    real = np.stack([project(POSE_3D, yaw) for yaw in YAWS_DEG]).astype(np.float32)
    mirrored = real[:, swap].copy()
    mirrored[..., 0] = 1000.0 - mirrored[..., 0]  # the image flipped left to right
    visible = np.ones(real.shape[:2], dtype=bool)
    lifted, lifted_mirror = bundled.lift(real, visible), bundled.lift(mirrored, visible)
    np.testing.assert_allclose(lifted_mirror.pose_3d, lifted.pose_3d[:, swap] * [-1, 1, 1], atol=0.05)
    # The critic judges the mirror image on its own (it is not mirror-symmetric): both are real poses.
    assert lifted.plausibility is not None and lifted_mirror.plausibility is not None
    assert np.all(lifted.plausibility > 0.9) and np.all(lifted_mirror.plausibility > 0.9)


def test_bundled_plausibility_gives_zero_to_a_pose_no_human_has(bundled: Lifter) -> None:
    bones = json.loads(bundled.info.metadata["plausibility_calibration"])["bone_length_range_mm"]
    names = json.loads(bundled.info.metadata["joint_names"])
    forearm = bones["bones"].index(["left_elbow", "left_wrist"])
    # The real test pose's forearm lies inside the range, and the range is that of people.
    length = float(np.linalg.norm(POSE_3D[names.index("left_wrist")] - POSE_3D[names.index("left_elbow")]))
    assert bones["shortest"][forearm] < length < bones["longest"][forearm] < 3 * length
