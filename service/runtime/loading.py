"""What a process loads before it lifts, each model checked: the bundled models' paths, the start-up
check of a single-frame model (known poses) and of a temporal model (trained on that model's answers,
a person standing still), and files read safely (regular files of bounded size, in chunks)."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np

from repnet.core.errors import ModelLoadError
from repnet.core.formats import MODEL_JOINTS
from repnet.core.inputs import EXAMPLE_KEYPOINTS
from repnet.runtime.lifter import Lifter
from repnet.runtime.plans import camera_poses
from repnet.runtime.session import HasSessionOptions, model_sha256
from repnet.runtime.temporal import TemporalLifter

log = logging.getLogger(__name__)

MODELS = Path(__file__).resolve().parents[1] / "models"  # the package's bundled models
BUNDLED_MODEL = MODELS / "repnet-h36m.onnx"
BUNDLED_CAUSAL = MODELS / "repnet-h36m-temporal-causal.onnx"
BUNDLED_OFFLINE = MODELS / "repnet-h36m-temporal-offline.onnx"


def check_lifter(lifter: Lifter) -> Lifter:
    """`lifter` once it passed the start-up check; ModelLoadError if it is not the h36m17 model the
    formats expect or fails on the known poses."""
    if lifter.info.joint_names != MODEL_JOINTS:
        raise ModelLoadError(
            f"{lifter.path}: joints {list(lifter.info.joint_names)} are not the h36m17 joints "
            f"{list(MODEL_JOINTS)} that the keypoint formats map onto"
        )
    lifter.check_outputs(*known_poses())
    return lifter


def file_sha256(path: Path) -> str:
    """The sha256 of the model file at `path` (what temporal models and lineage name a model by):
    a regular file of bounded size, read in chunks (session.model_sha256)."""
    return model_sha256(path)


MAX_LINEAGE = 64  # parents followed up a model's lineage (an adapted model of an adapted model...)


def ancestors(metadata: dict[str, str]) -> list[str]:
    """The sha256 of each model a model was adapted from (`repnet adapt`'s lineage metadata: its
    parent, then the parent's parent...), nearest first; [] for a model not adapted."""
    try:
        record: Any = json.loads(metadata.get("lineage", "") or "null")
    except json.JSONDecodeError:
        return []
    found: list[str] = []
    while isinstance(record, dict) and len(found) < MAX_LINEAGE:
        parent = record.get("parent")
        sha = parent.get("sha256") if isinstance(parent, dict) else None
        if not isinstance(sha, str) or not sha:
            break
        found.append(sha)
        record = record.get("parent_lineage")
    return found


def serves_under(base_sha256: str, sha256: str, metadata: dict[str, str]) -> bool:
    """Whether a temporal model trained on the answers of the single-frame model of file hash
    `base_sha256` (its metadata's base_model_sha256) runs over the one of file hash `sha256` and
    `metadata`: that model, or one adapted from it (`repnet adapt`: the temporal models work
    unchanged over an adapted model, docs/RESULTS.md)."""
    return base_sha256 in (sha256, *ancestors(metadata))


def load_temporal_lifters(
    model_path: Path,
    lifter: Lifter,
    paths: dict[str, Path],
    settings: HasSessionOptions | None = None,
) -> dict[str, TemporalLifter]:
    """The temporal models at `paths` by mode ("causal", "offline"), checked: each must be the mode
    it is given as, trained on the answers of `lifter` (loaded from `model_path`: its sha256) or of a
    model it was adapted from (serves_under), and pass its start-up check. A bundled temporal model
    that is missing or belongs to another single-frame model is left out with a warning; another
    that does not fit raises ModelLoadError."""
    found: dict[str, TemporalLifter] = {}
    base = file_sha256(model_path)
    bundled = {"causal": BUNDLED_CAUSAL, "offline": BUNDLED_OFFLINE}
    for mode, path in paths.items():
        if path == bundled[mode] and not path.is_file():
            log.warning("no %s temporal model (%s): tracked poses are lifted alone", mode, path)
            continue
        temporal = TemporalLifter.load(path, settings)
        if temporal.mode != mode:
            raise ModelLoadError(f"{path}: a {temporal.mode} temporal model, set as the {mode} one")
        if not serves_under(temporal.base_model_sha256, base, lifter.info.metadata):
            message = (
                f"{path}: trained on the answers of the single-frame model with sha256 "
                f"{temporal.base_model_sha256[:12]}, not of {model_path.name} ({base[:12]})"
            )
            if path == bundled[mode]:
                log.warning("%s: the %s temporal model is left out", message, mode)
                continue
            raise ModelLoadError(message)
        check_temporal(temporal, lifter)
        found[mode] = temporal
    return found


def check_temporal(temporal: TemporalLifter, lifter: Lifter) -> None:
    """The temporal model's start-up check on the single-frame answers to the known poses."""
    points, visibility = known_poses()
    prediction = lifter.lift(points, visibility)
    poses = camera_poses(prediction, np.arange(len(points)))
    keypoints = np.where(visibility[..., None], points, 0.0).astype(np.float32)
    temporal.check_outputs(poses, keypoints, visibility.astype(np.float32))


def known_poses() -> tuple[np.ndarray, np.ndarray]:
    """The check every model passes at start: the OpenAPI example person (N, 17, 2) px, its mirror
    image, and the person without spine and head (as COCO detectors give it), with visibility."""
    person = np.array(EXAMPLE_KEYPOINTS, dtype=np.float32)  # (17, 2)
    mirrored = person * [-1.0, 1.0] + [2 * person[:, 0].mean(), 0.0]
    visibility = np.ones((3, len(MODEL_JOINTS)), dtype=bool)
    visibility[2, [MODEL_JOINTS.index("spine"), MODEL_JOINTS.index("head")]] = False
    return np.stack([person, mirrored, person]).astype(np.float32), visibility
