"""The bundled model itself: its plausibility output and how it orders real and broken poses."""

from __future__ import annotations

import json

import numpy as np
import pytest

from repnet.runtime.lifter import Lifter
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
    table = calibration["scores_at_quantiles"]
    assert len(table) == calibration["levels"] > 100 and table == sorted(table)
    assert calibration["score"] == "density"
    assert "real" in meta["plausibility"]


def test_a_limb_30_percent_longer_in_the_image_is_turned_in_the_answer_and_a_turned_shin_is_less_plausible(
    bundled: Lifter,
) -> None:
    """The lifter keeps a person's bones: it explains a limb 30 % longer in the image by turning it
    (every answer keeps the real answer's bone lengths within 2 %). So the plausibility judges the
    turned limb: a forearm can point anywhere (no claim), a shin turned out of the leg's plane bends
    the knee as knees do not, and must score lower than the real answer."""
    cases = [(name, yaw) for name in LIMBS for yaw in YAWS_DEG]
    real = np.stack([project(POSE_3D, yaw) for _, yaw in cases]).astype(np.float32)
    broken = np.stack([project(_stretched(POSE_3D, *LIMBS[name], 1.3), yaw) for name, yaw in cases]).astype(
        np.float32
    )
    visible = np.ones(real.shape[:2], dtype=bool)
    lifted_real, lifted_broken = bundled.lift(real, visible), bundled.lift(broken, visible)
    for i, (name, _) in enumerate(cases):
        parent, child = LIMBS[name]
        lengths = [
            np.linalg.norm(p.pose_3d[i, child] - p.pose_3d[i, parent]) for p in (lifted_real, lifted_broken)
        ]
        assert abs(lengths[1] / lengths[0] - 1) < 0.02, (name, lengths)
    p_real, p_broken = lifted_real.plausibility, lifted_broken.plausibility
    assert p_real is not None and p_broken is not None
    assert np.all((p_real >= 0) & (p_real <= 1)) and np.all((p_broken >= 0) & (p_broken <= 1))
    shins = [i for i, (name, _) in enumerate(cases) if "shin" in name]
    worse = [cases[i] for i in shins if not p_real[i] > p_broken[i]]
    assert not worse, f"a turned shin not ranked below the real pose for {worse}"


def test_garbage_input_is_flagged_implausible(bundled: Lifter) -> None:
    real = np.stack([project(POSE_3D, yaw) for yaw in YAWS_DEG]).astype(np.float32)
    swapped = real.copy()
    swapped[:, [3, 16]] = real[:, [16, 3]]  # right ankle and right wrist exchanged
    visible = np.ones(real.shape[:2], dtype=bool)
    lifted_real, lifted_swapped = bundled.lift(real, visible), bundled.lift(swapped, visible)
    p_real, p_swapped = lifted_real.plausibility, lifted_swapped.plausibility
    assert p_real is not None and p_swapped is not None
    # repnet-h36m-v2 lifted this input to a wild pose (plausibility 0.0, reprojection error
    # 580-1780 px); v3 to v7 lift it to a body-like pose that cannot fit the input: below most
    # real poses (v7's density: 0 for all three views; the real ones 0.83-0.90, in the top fifth
    # of real poses) and with several times the reprojection error of the real input.
    assert np.all(p_real > 0.8) and np.all(p_swapped < 0.3)
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
    # The plausibility judges the mirror image on its own (the pose density is fitted to the training
    # poses as they are, not mirror-symmetric): both are typical real poses.
    assert lifted.plausibility is not None and lifted_mirror.plausibility is not None
    assert np.all(lifted.plausibility > 0.8) and np.all(lifted_mirror.plausibility > 0.8)


def test_bundled_plausibility_gives_zero_to_a_pose_no_human_has(bundled: Lifter) -> None:
    bones = json.loads(bundled.info.metadata["plausibility_calibration"])["bone_length_range_mm"]
    names = json.loads(bundled.info.metadata["joint_names"])
    forearm = bones["bones"].index(["left_elbow", "left_wrist"])
    # The real test pose's forearm lies inside the range, and the range is that of people.
    length = float(np.linalg.norm(POSE_3D[names.index("left_wrist")] - POSE_3D[names.index("left_elbow")]))
    assert bones["shortest"][forearm] < length < bones["longest"][forearm] < 3 * length
