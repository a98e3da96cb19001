"""What start-up loads, each checked: the default model, the models of REPNET_MODEL_DIR, the
temporal models (trained on the default one's answers) behind their batchers."""

from __future__ import annotations

import hashlib
import logging
from pathlib import Path

import numpy as np

from service.config import BUNDLED_CAUSAL, BUNDLED_OFFLINE, Settings
from service.engine import TemporalEngine
from service.errors import ModelLoadError
from service.formats import MODEL_JOINTS
from service.lifter import Lifter, open_session
from service.metrics import Metrics
from service.schemas import EXAMPLE_KEYPOINTS
from service.temporal import TemporalLifter
from service.tracking import TemporalModels, camera_poses
from service.tracks import TrackBudget

log = logging.getLogger("service")


def load_lifter(settings: Settings) -> Lifter:
    """The default model, from settings.model_path, checked (check_lifter)."""
    return check_lifter(Lifter.load(settings.model_path, settings))


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
    """The sha256 of the file at `path` (what temporal models and lineage name a model by)."""
    return hashlib.sha256(path.read_bytes()).hexdigest()


def load_dir_lifters(settings: Settings, default: Lifter) -> list[Lifter]:
    """The single-frame models of settings.model_dir (*.onnx, by file name), each checked as the
    default is, beside `default`. A file that fails to load or its check stops the start
    (ModelLoadError, one line naming the file): a service that quietly serves fewer models than
    its operator put there would answer `unknown model` to the clients that name the missing one.
    Temporal models (metadata kind temporal) are left out (with a log line): REPNET_CAUSAL_MODEL_PATH
    and REPNET_OFFLINE_MODEL_PATH set those. A file with the same bytes as a model already loaded
    (the bundled one copied in) is served once; two different files with one model_id stop the start."""
    directory = settings.model_dir
    if directory is None:
        return []
    if not directory.is_dir():
        raise ModelLoadError(f"REPNET_MODEL_DIR {directory} is not a directory")
    loaded = {default.info.model_id: (default.path, file_sha256(default.path))}
    found = []
    for path in sorted(directory.glob("*.onnx")):
        digest = file_sha256(path)
        if same := [m for m, (_, d) in loaded.items() if d == digest]:
            log.info("%s: the same file as model %s, served once", path, same[0])
            continue
        try:
            session = open_session(path, settings)
            if session.get_modelmeta().custom_metadata_map.get("kind") == "temporal":
                log.info("%s: a temporal model, not served by name (REPNET_CAUSAL_MODEL_PATH, ...)", path)
                continue
            lifter = check_lifter(Lifter(session, path))
        except ModelLoadError as err:
            raise ModelLoadError(f"REPNET_MODEL_DIR: {' '.join(str(err).split())}") from None
        if (other := loaded.get(lifter.info.model_id)) is not None:
            raise ModelLoadError(
                f"REPNET_MODEL_DIR: {path} has model_id {lifter.info.model_id!r}, as {other[0]} has: "
                "each model served needs an id of its own (ONNX metadata model_id)"
            )
        log.info("loaded model %s (%s) from %s", lifter.info.model_id, lifter.info.skeleton, path)
        loaded[lifter.info.model_id] = (path, digest)
        found.append(lifter)
    return found


def load_temporal_lifters(settings: Settings, lifter: Lifter) -> dict[str, TemporalLifter]:
    """The temporal models of the settings by mode, checked: each must be the mode its setting names,
    trained on the answers of the loaded single-frame model (its sha256) and pass its start-up check. A
    bundled temporal model that is missing or belongs to another single-frame model is left out with
    a warning; a temporal model named in the settings that does not fit stops the start."""
    if not settings.temporal:
        return {}
    found: dict[str, TemporalLifter] = {}
    base = file_sha256(settings.model_path)  # the default model's file, which `lifter` was loaded from
    for mode, path, bundled in (
        ("causal", settings.causal_model_path, BUNDLED_CAUSAL),
        ("offline", settings.offline_model_path, BUNDLED_OFFLINE),
    ):
        if path == bundled and not path.is_file():
            log.warning("no %s temporal model (%s): tracked poses are lifted alone", mode, path)
            continue
        temporal = TemporalLifter.load(path, settings)
        if temporal.mode != mode:
            raise ModelLoadError(f"{path}: a {temporal.mode} temporal model, set as the {mode} one")
        if temporal.base_model_sha256 != base:
            message = (
                f"{path}: trained on the answers of the single-frame model with sha256 "
                f"{temporal.base_model_sha256[:12]}, not of {settings.model_path.name} ({base[:12]})"
            )
            if path == bundled:
                log.warning("%s: the %s temporal model is left out", message, mode)
                continue
            raise ModelLoadError(message)
        check_temporal(temporal, lifter)
        found[mode] = temporal
    return found


def load_temporal(settings: Settings, lifter: Lifter, metrics: Metrics) -> TemporalModels | None:
    """The temporal models of the settings (load_temporal_lifters), each behind its own batcher, and
    the bounds on their tracks; None without any."""
    lifters = load_temporal_lifters(settings, lifter)
    if not lifters:
        return None
    engines = {
        mode: TemporalEngine(
            temporal,
            max_batch=settings.max_batch,
            max_wait_s=settings.max_wait_ms / 1000,
            queue_size=settings.queue_size,
        )
        for mode, temporal in lifters.items()
    }
    budget = TrackBudget(settings.max_tracks, metrics.set_tracks)
    return TemporalModels(
        engines,
        budget,
        settings.stream_max_tracks,
        settings.track_idle_s,
        min(settings.max_temporal_poses, settings.queue_size),  # a larger request could never be queued
    )


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
