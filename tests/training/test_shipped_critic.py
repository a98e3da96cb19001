"""The 3D priors inside the shipped model: the score behind its plausibility output (the pose
density) and the critic (the adversarial prior of adaptation). Each should score a real pose
above the same body broken in the ways a lifter breaks it."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from repnet.runtime.loading import BUNDLED_MODEL
from repnet.train import checkpoint, data
from repnet.train.density import PoseDensity
from repnet.train.export import load_critic
from repnet.train.model import MM_PER_UNIT
from tests.conftest import POSE_3D

# (parent, child) of the arm and leg bones; the joints below child move with it when it stretches.
LIMBS = {
    "right thigh": (1, 2),
    "right shin": (2, 3),
    "left thigh": (4, 5),
    "left shin": (5, 6),
    "left upper arm": (11, 12),
    "left forearm": (12, 13),
    "right upper arm": (14, 15),
    "right forearm": (15, 16),
}
BELOW = {2: (2, 3), 3: (3,), 5: (5, 6), 6: (6,), 12: (12, 13), 13: (13,), 15: (15, 16), 16: (16,)}
LEFT_ARM, RIGHT_ARM = [11, 12, 13], [14, 15, 16]


def _phoning() -> np.ndarray:
    """POSE_3D (template frame, mm: x right, y down, z away from the camera, the person facing it)
    with the left elbow bent 90 degrees and the forearm pointing forward, as when phoning."""
    pose = POSE_3D.copy()
    pose[12] = [215, -190, 30]
    pose[13] = [225, -210, -210]
    return pose


def _heel_up() -> np.ndarray:
    """POSE_3D with the right knee bent 90 degrees: thigh down, shin pointing backwards."""
    pose = POSE_3D.copy()
    pose[2] = [-135, 430, -20]
    pose[3] = [-135, 460, 410]
    return pose


def _stretched(pose: np.ndarray, parent: int, child: int, factor: float = 1.3) -> np.ndarray:
    out = pose.copy()
    out[list(BELOW[child])] += (factor - 1) * (pose[child] - pose[parent])
    return out


def _depth_flipped(pose: np.ndarray, parent: int, child: int) -> np.ndarray:
    """The limb end mirrored through its joint along depth: the 2D is the same, the joint bends the
    wrong way (the ambiguity a lifter must resolve)."""
    out = pose.copy()
    out[child, 2] = 2 * pose[parent, 2] - pose[child, 2]
    return out


def _arms_swapped(pose: np.ndarray) -> np.ndarray:
    out = pose.copy()
    out[LEFT_ARM + RIGHT_ARM] = pose[RIGHT_ARM + LEFT_ARM]
    return out


def _scores(score: torch.nn.Module, poses: list[np.ndarray]) -> np.ndarray:
    """Scores of (17, 3) mm poses, aligned onto the template torso as the real ones were."""
    aligned = data.align_to_template(np.stack(poses))
    with torch.no_grad():
        return score(torch.from_numpy(aligned / MM_PER_UNIT)).numpy()


@pytest.fixture(scope="module")
def state() -> dict[str, Any]:
    return checkpoint.load(Path(os.environ.get("REPNET_MODEL_PATH", BUNDLED_MODEL)))


def _wrong(score: torch.nn.Module) -> list[str]:
    """The cases in which the broken pose scores at least as high as the real one."""
    cases = _pairs()
    real = _scores(score, [r for _, r, _ in cases])
    broken = _scores(score, [b for _, _, b in cases])
    return [
        f"{what} ({r:.3f} <= {b:.3f})"
        for (what, _, _), r, b in zip(cases, real, broken, strict=True)
        if not r > b
    ]


def _pairs() -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(what, real pose, the same pose broken)."""
    cases = []
    for name, real in (("standing", POSE_3D), ("phoning", _phoning()), ("heel up", _heel_up())):
        cases += [(f"{name}: {limb} 30 % longer", real, _stretched(real, *LIMBS[limb])) for limb in LIMBS]
        cases.append((f"{name}: left and right arm swapped", real, _arms_swapped(real)))
    cases.append(("phoning: left forearm flipped in depth", _phoning(), _depth_flipped(_phoning(), 12, 13)))
    cases.append(("heel up: right shin flipped in depth", _heel_up(), _depth_flipped(_heel_up(), 2, 3)))
    return cases


def test_the_shipped_plausibility_scores_a_real_pose_above_it_with_a_limb_stretched_swapped_or_flipped(
    state: dict[str, Any],
) -> None:
    if not state["density"]:
        pytest.skip("the model's plausibility is not the pose density")
    wrong = _wrong(PoseDensity.of_state(state["density"]))
    assert not wrong, f"the pose density does not rank the real pose higher: {wrong}"


@pytest.mark.xfail(
    strict=True,
    reason="the critic of repnet-h36m-v6 and v7 (v2's recipe) ranks 2 of the 29 cases wrong: standing "
    "with the left forearm 30 % longer (1.590 vs 1.591) and heel up with the right thigh 30 % longer "
    "(1.308 vs 1.399); no critic trained so far passes them all (docs/RESULTS.md, Plausibility critic, "
    "round 2), so since v7 the plausibility output ranks by the pose density instead. Strict: a critic "
    "that passes makes this test fail until the mark is removed.",
)
def test_the_shipped_critic_scores_a_real_pose_above_it_with_a_limb_stretched_swapped_or_flipped(
    state: dict[str, Any],
) -> None:
    if not state["critic"]:
        pytest.skip("the model carries no critic")
    wrong = _wrong(load_critic(state))
    assert not wrong, f"the critic does not rank the real pose higher: {wrong}"


def test_the_broken_poses_are_what_they_say() -> None:
    """The cases change what they name and keep everything else (so the ranking test means it)."""
    real = _phoning()
    stretched = _stretched(real, 11, 12)
    bone = np.linalg.norm(stretched[12] - stretched[11]) / np.linalg.norm(real[12] - real[11])
    np.testing.assert_allclose(bone, 1.3)
    np.testing.assert_allclose(stretched[13] - stretched[12], real[13] - real[12])  # forearm moved along
    flipped = _depth_flipped(real, 12, 13)
    np.testing.assert_allclose(flipped[:, :2], real[:, :2])  # the same image
    assert flipped[13, 2] - flipped[12, 2] == -(real[13, 2] - real[12, 2]) > 0  # the forearm now points back
    swapped = _arms_swapped(real)
    np.testing.assert_array_equal(swapped[LEFT_ARM], real[RIGHT_ARM])
    np.testing.assert_array_equal(swapped[: LEFT_ARM[0]], real[: LEFT_ARM[0]])
