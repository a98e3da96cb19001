"""What an exported model file says of itself: its ONNX metadata (joints, skeleton, units, the camera
contract, provenance, licence, figures) and the words for how and on what it was trained."""

from __future__ import annotations

import json
from dataclasses import asdict
from typing import Any

from repnet.core import skeleton
from repnet.runtime.lifter import TRAINING_METHOD
from repnet.train import checkpoint
from repnet.train.config import RepNetConfig

LICENCE = (
    "Weights trained on Human3.6M (Ionescu et al., TPAMI 2014): academic, non-commercial "
    "research use only, under the Human3.6M licence. The code is Apache-2.0."
)


def build_metadata(
    config: RepNetConfig,
    model_id: str,
    train_command: str = "",
    training_data: str = "",
    evaluation: dict[str, Any] | None = None,
    plausibility: dict[str, str] | None = None,
    mirror_average: bool = False,
    lineage: dict[str, Any] | None = None,
    training_method: str = "",
) -> dict[str, str]:
    """ONNX custom metadata: joints, skeleton, provenance (train_command, how it was trained and,
    given, the lineage as JSON), licence, evaluation figures and, with a plausibility output, what it
    means and its calibration (repnet.train.plausibility.metadata's entries)."""
    extra: dict[str, str] = {} if lineage is None else {"lineage": json.dumps(lineage)}
    extra.update(plausibility or {})
    return {
        "model_id": model_id,
        "joint_names": json.dumps(list(skeleton.JOINT_NAMES)),
        "parents": json.dumps(list(skeleton.PARENTS)),
        "skeleton": "h36m17",
        "units": "pose_3d in mm, pelvis at origin, template frame (x right, y down, z away from camera)",
        "camera_contract": "camera K (2x3) maps pose_3d onto the input centred on its visible joints "
        "and divided by their standard deviation, up to a translation",
        "model_config": json.dumps(asdict(config)),
        "training_data": training_data,
        TRAINING_METHOD: training_method,
        "licence": LICENCE,
        "train_command": train_command,
        "evaluation": json.dumps(evaluation or {}),
        "mirror_average": json.dumps(mirror_average),
        **extra,
    }


def training_data(inputs: str, exclude_actions: str = "") -> str:
    """The metadata entry `training_data`: "Human3.6M S1 S5 S6 S7 S8, 2D inputs: gt+sh", with " without
    the actions Sitting,SittingDown" after the subjects when the run left those out
    (checkpoint.from_onnx reads both back)."""
    without = f"{checkpoint.EXCLUDED_ACTIONS}{exclude_actions}" if exclude_actions else ""
    return f"Human3.6M S1 S5 S6 S7 S8{without}, 2D inputs: {inputs}"


def method_of(train: dict[str, Any]) -> str:
    """How a run of TrainConfig `train` (its checkpoint's config) trained the generator, in words."""
    supervised = int(train.get("warm_start_steps", 0))
    if supervised >= int(train.get("iterations", 0)):
        return (
            "Supervised on synthetic projections of Human3.6M 3D poses (the training subjects through "
            "random cameras): the adversarial phase is empty. The paper's weakly supervised losses are "
            "used by `repnet adapt`."
        )
    return (
        f"{supervised} steps supervised on synthetic projections of Human3.6M 3D poses, then the paper's "
        "weak supervision: the reprojection and camera losses on 2D inputs and the WGAN-GP critic."
    )
