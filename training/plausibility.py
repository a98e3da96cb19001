"""The plausibility output: what scores a pose, its calibration among real poses, its metadata.

A score (the pose density, repnet.train.density, or in models exported before it the critic) becomes
a percentile among the real validation poses (model.Plausibility), and a pose with a bone outside
the real poses' range scores 0. export builds it from the Human3.6M data; adapt rebuilds a parent's
from its file (from_state).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import torch
from torch import nn

from repnet.core import skeleton
from repnet.train.density import PoseDensity
from repnet.train.losses import bone_lengths
from repnet.train.model import MM_PER_UNIT, Plausibility, load_critic

CALIBRATION_LEVELS = 1001  # quantiles of the score over real poses: 0.1 % steps
# A real pose's bone may be this much shorter than the shortest or longer than the longest of
# that bone among the real validation poses (template-aligned, so relative to the torso) before
# plausibility calls the pose impossible: people beyond the five training subjects differ.
BONE_MARGIN = 1.5

Score = Literal["density", "critic"]
SCORES: tuple[Score, ...] = ("density", "critic")


@dataclass(frozen=True)
class DensityConfig:
    """How the pose density is fitted: to every frame_step-th training pose (the validation tails
    left out), `components` Gaussians in `dims` PCA dimensions (chosen on validation, RESULTS.md)."""

    frame_step: int = 5
    components: int = 64
    dims: int = 32
    seed: int = 0


def calibrate(score: nn.Module, real_poses_mm: np.ndarray, levels: int = CALIBRATION_LEVELS) -> np.ndarray:
    """The scores of real template-aligned (N, J, 3) poses (mm) at `levels` evenly spaced
    quantiles, 0 to 100 %: the table that turns a score into its percentile among real poses."""
    with torch.no_grad():
        scores = score(torch.from_numpy(real_poses_mm.astype(np.float32) / MM_PER_UNIT)).numpy()
    return np.quantile(scores.astype(np.float64), np.linspace(0.0, 1.0, levels)).astype(np.float32)


def bone_range(real_poses_mm: np.ndarray, margin: float = BONE_MARGIN) -> np.ndarray:
    """(2, B) shortest / margin and longest * margin length (metres) of each bone over real
    template-aligned (N, J, 3) poses (mm): outside it, Plausibility scores 0."""
    lengths = bone_lengths(torch.from_numpy(real_poses_mm.astype(np.float32) / MM_PER_UNIT)).numpy()
    return np.stack([lengths.min(axis=0) / margin, lengths.max(axis=0) * margin]).astype(np.float32)


def build(score: nn.Module, real_poses_mm: np.ndarray) -> tuple[Plausibility, np.ndarray, np.ndarray]:
    """The calibrated Plausibility of `score` over real validation poses, its table and bone range."""
    table, bones = calibrate(score, real_poses_mm), bone_range(real_poses_mm)
    return Plausibility(score, torch.from_numpy(table), torch.from_numpy(bones)), table, bones


DESCRIPTIONS = {
    "density": "the pose density (a Gaussian mixture over bone directions and relative bone lengths, "
    "fitted to the training poses) ranks this pose_3d at or above",
    "critic": "the trained critic scores at most as high as this pose_3d",
}


def metadata(score: Score, table: np.ndarray, bones: np.ndarray | None) -> dict[str, str]:
    """The ONNX metadata entries `plausibility` (what the output means) and
    `plausibility_calibration` (the table and the bone range, JSON)."""
    what = (
        "plausibility (N,) in [0, 1]: the share of real Human3.6M validation poses (template-aligned "
        f"ground truth of held-out training-subject frames) that {DESCRIPTIONS[score]}; 0.5 is a "
        "typical real pose, below 0.05 fewer than 1 in 20 real poses look as implausible"
    )
    calibration: dict[str, Any] = {
        "score": score,
        "levels": len(table),
        "scores_at_quantiles": [round(float(v), 6) for v in table],
        "reference": f"{score} scores of real validation poses, at quantiles 0..1 evenly spaced",
    }
    if bones is not None:
        calibration["bone_length_range_mm"] = {
            "bones": [[skeleton.JOINT_NAMES[p], skeleton.JOINT_NAMES[c]] for p, c in skeleton.BONES],
            "shortest": [round(float(v) * MM_PER_UNIT, 1) for v in bones[0]],
            "longest": [round(float(v) * MM_PER_UNIT, 1) for v in bones[1]],
            "rule": "plausibility is 0 when any bone of pose_3d is outside [shortest, longest]: the "
            f"range of that bone over the real validation poses, widened {BONE_MARGIN}x each way",
        }
    return {"plausibility": what, "plausibility_calibration": json.dumps(calibration)}


def from_state(state: dict[str, Any], meta: dict[str, str]) -> Plausibility:
    """A model's plausibility rebuilt from its file: its state (checkpoint.load of the .onnx: the
    density or critic weights) and metadata (the calibration table and bone range)."""
    if "plausibility_calibration" not in meta:
        raise ValueError("the model has no plausibility output (export it with plausibility)")
    calibration = json.loads(meta["plausibility_calibration"])
    # Models exported before the density name the critic's table "critic_scores_at_quantiles".
    kind = calibration.get("score", "critic")
    table = calibration.get("scores_at_quantiles", calibration.get("critic_scores_at_quantiles"))
    score = PoseDensity.of_state(state["density"]) if kind == "density" else load_critic(state)
    bones = None
    if "bone_length_range_mm" in calibration:
        ranges = calibration["bone_length_range_mm"]
        bones = torch.tensor([ranges["shortest"], ranges["longest"]], dtype=torch.float32) / MM_PER_UNIT
    return Plausibility(score.eval(), torch.tensor(table, dtype=torch.float32), bones).eval()
