"""The bundled model itself: its plausibility output and how it orders real and broken poses."""

from __future__ import annotations

import json

import numpy as np
import pytest

from service.lifter import Lifter
from tests.conftest import POSE_3D, project

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
    # 580-1780 px); v3 lifts it to a body-like pose that cannot fit the input: below most real
    # poses (0.21-0.24) and with 8x the reprojection error of the real input.
    assert np.all(p_real > 0.9) and np.all(p_swapped < 0.3)
    assert np.all(lifted_swapped.reprojection_error_px > 5 * lifted_real.reprojection_error_px)
