"""What `repnet adapt` says and writes at the end: figures on the held-out part of the user's 2D
before and after, the rule that refuses a worse model, and the adapted ONNX with its lineage.

The figures need no 3D truth: how far the answer's reprojection K X lies from the 2D (px), how
plausible the parent's plausibility finds the answers (the parent's for both, so the numbers
compare), and two properties a person's skeleton has: left equals right (symmetry, mm) and a
track's limbs keep their length (bone-length spread over the held-out poses, mm).
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from repnet.runtime.lifter import TRAINING_METHOD, training_method_of
from repnet.train import metrics, plausibility
from repnet.train.adapt import answer
from repnet.train.export import check_parity, export_onnx, parity_inputs
from repnet.train.model import MM_PER_UNIT, Critic, Plausibility, RepNet
from repnet.train.sequences import pose_spread


@dataclass(frozen=True)
class Figures:
    """One model's figures on the held-out 2D."""

    reprojection_px: float  # mean over visible joints of |W - K X| in pixels
    plausibility: float  # mean of the parent's plausibility in [0, 1]
    implausible_pct: float  # % of answers the parent's plausibility calls implausible (< 0.05)
    symmetry_mm: float  # mean |left - right| limb length
    bone_std_mm: float  # mean over limbs of the std of its length over the poses


# How much worse a figure may get before the model is refused (reprojection: a share of the parent's;
# implausible answers: percentage points). Plausibility's mean is reported, not judged: real poses
# average 0.5, and a lifter's answers that lean toward the average pose score above that, so a
# mean that falls towards 0.5 is no sign of worse answers; more answers below 0.05 are.
TOLERANCE = {"reprojection_px": 0.10, "implausible_pct": 1.0, "symmetry_mm": 1.0, "bone_std_mm": 1.0}
IMPLAUSIBLE = 0.05  # the service's meaning: fewer than 1 in 20 real poses look as implausible
# The fewest held-out poses on which the refusal can tell a worse model from chance: one answer that
# turns implausible moves implausible_pct by 100 / n points, within its tolerance from n = 100 on.
MIN_HOLDOUT = math.ceil(100 / TOLERANCE["implausible_pct"])


def parent_scorer(state: dict[str, Any], meta: dict[str, str]) -> Plausibility:
    """The parent's plausibility (its score: the pose density or the critic, calibration table and
    bone range) as a module; ValueError when the parent has no critic or no plausibility."""
    if not state.get("critic") or "plausibility_calibration" not in meta:
        raise ValueError(
            "the parent model has no critic or no plausibility output: adapt needs both (export it "
            "with plausibility)"
        )
    return plausibility.from_state(state, meta)


def measure(
    generator: RepNet, scorer: Plausibility, points: np.ndarray, visible: np.ndarray, mirror_average: bool
) -> Figures:
    """A generator's figures on (N, J, 2) pixel points and (N, J) visibility."""
    pose, _, residual = answer(generator, points, visible, mirror_average)
    spread = pose_spread(points, visible)  # px per unit of the normalised input
    per_joint = np.linalg.norm(residual, axis=-1) * spread[:, None]  # (N, J) px, 0 where hidden
    with torch.no_grad():
        plausible = scorer(torch.from_numpy(pose) / MM_PER_UNIT).numpy()
    return Figures(
        reprojection_px=float(per_joint.sum() / max(visible.sum(), 1.0)),
        plausibility=float(plausible.mean()),
        implausible_pct=100.0 * float((plausible < IMPLAUSIBLE).mean()),
        symmetry_mm=float(metrics.symmetry_error(pose).mean()),
        bone_std_mm=float(metrics.limb_length_std(pose).mean()),
    )


# Each figure's name, unit and decimals, in the report's order.
WORDS = {
    "reprojection_px": ("reprojection error", "px", 2),
    "plausibility": ("plausibility", "parent's", 3),
    "implausible_pct": ("implausible answers", "%", 1),
    "symmetry_mm": ("symmetry error", "mm", 1),
    "bone_std_mm": ("bone-length spread", "mm", 1),
}


def worse(before: Figures, after: Figures) -> list[str]:
    """The figures that got worse beyond TOLERANCE, in words (empty: the model may be written)."""
    reasons = []
    for key, tolerance in TOLERANCE.items():
        was, now = getattr(before, key), getattr(after, key)
        # The reprojection error may grow by a share of itself; the others by an amount.
        if now > (was * (1 + tolerance) if key == "reprojection_px" else was + tolerance):
            name, unit, digits = WORDS[key]
            reasons.append(f"{name} rose from {was:.{digits}f} to {now:.{digits}f} {unit}")
    return reasons


def render(before: Figures, after: Figures, poses: int) -> str:
    """The before/after table the command prints."""
    lines = [f"held-out poses: {poses}", f"{'':32}{'before':>10}{'after':>10}"]
    for key, (name, unit, digits) in WORDS.items():
        label = f"{name} ({unit})"
        lines.append(f"{label:32}{getattr(before, key):>10.{digits}f}{getattr(after, key):>10.{digits}f}")
    return "\n".join(lines)


def export_adapted(
    generator: RepNet,
    scorer: Plausibility,
    parent_meta: dict[str, str],
    output: Path,
    lineage: dict[str, Any],
    mirror_average: bool,
    critic: Critic | None = None,
) -> float:
    """Write the adapted generator with the parent's plausibility and metadata, its own model id
    and lineage (lineage["model_id"]), and the adapted critic as the "critic" output when given;
    returns torch vs onnxruntime's max |diff| (mm)."""
    meta = dict(parent_meta)
    meta["model_id"] = lineage["model_id"]
    meta["train_command"] = lineage["command"]
    parent_data = parent_meta.get("training_data", "")
    meta["training_data"] = f"{parent_data}; adapted (repnet adapt) on {lineage['poses']} unlabeled 2D poses"
    meta[TRAINING_METHOD] = (
        f"{training_method_of(parent_meta)} Then adapted by `repnet adapt`: the paper's weakly supervised "
        f"losses (reprojection, camera, WGAN-GP critic with its KCS path) on {lineage['poses']} unlabeled "
        "2D poses, with an anchor to the parent's answers."
    ).strip()
    meta["evaluation"] = json.dumps({"adapt_holdout": lineage["report"]})
    meta["lineage"] = json.dumps(lineage)
    export_onnx(generator.eval(), output, meta, scorer, mirror_average, critic)
    return check_parity(generator, output, *parity_inputs(), mirror_average)


def report_record(before: Figures, after: Figures, poses: int) -> dict[str, Any]:
    """The report as the lineage keeps it."""
    return {"poses": poses, "before": asdict(before), "after": asdict(after)}
