"""What start-up loads, each checked: the default model, the models of REPNET_MODEL_DIR, the
temporal models (trained on the default one's answers) behind their batchers."""

from __future__ import annotations

import logging
from pathlib import Path

from repnet.core.errors import ModelLoadError
from repnet.runtime import loading
from repnet.runtime.lifter import Lifter
from repnet.runtime.loading import check_lifter, file_sha256
from repnet.runtime.plans import TemporalModels
from repnet.runtime.session import open_session
from repnet.runtime.temporal import TemporalBatcher, TemporalLifter
from repnet.runtime.tracks import TrackBudget
from repnet.server.config import Settings
from repnet.server.metrics import Metrics

log = logging.getLogger("repnet.server")


def load_lifter(settings: Settings) -> Lifter:
    """The default model, from settings.model_path, checked (check_lifter)."""
    return check_lifter(Lifter.load(settings.model_path, settings))


def load_dir_lifters(settings: Settings, default: Lifter) -> list[Lifter]:
    """The single-frame models of settings.model_dir (model_files), each checked as the
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
    for path in model_files(directory):
        try:
            digest = file_sha256(path)
            if same := [m for m, (_, d) in loaded.items() if d == digest]:
                log.info("%s: the same file as model %s, served once", path, same[0])
                continue
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


def model_files(directory: Path) -> list[Path]:
    """The model files of a model folder: its entries named *.onnx in any case (`UPPER.ONNX` too), by
    name. Hidden files (a leading dot) are left out; what each entry is (a regular file of bounded
    size) is checked when it is read (runtime.session.open_model_file)."""
    found = [p for p in directory.iterdir() if p.suffix.lower() == ".onnx" and not p.name.startswith(".")]
    return sorted(found)


def load_temporal_lifters(settings: Settings, lifter: Lifter) -> dict[str, TemporalLifter]:
    """The temporal models the settings name (none with temporal off), checked
    (runtime.loading.load_temporal_lifters): a bundled one that is missing or belongs to another
    single-frame model is left out with a warning; another that does not fit stops the start."""
    if not settings.temporal:
        return {}
    paths = {"causal": settings.causal_model_path, "offline": settings.offline_model_path}
    return loading.load_temporal_lifters(settings.model_path, lifter, paths, settings)


def load_temporal(settings: Settings, lifter: Lifter, metrics: Metrics) -> TemporalModels | None:
    """The temporal models of the settings (load_temporal_lifters), each behind its own batcher, and
    the bounds on their tracks; None without any."""
    lifters = load_temporal_lifters(settings, lifter)
    if not lifters:
        return None
    engines = {
        mode: TemporalBatcher(
            temporal,
            max_batch=settings.max_batch,
            max_wait_s=settings.max_wait_ms / 1000,
            queue_size=settings.queue_size,
            company_wait_s=settings.company_wait_ms / 1000,
        )
        for mode, temporal in lifters.items()
    }
    budget = TrackBudget(settings.max_tracks, metrics.set_tracks, settings.track_memory_mb << 20)
    return TemporalModels(
        engines,
        budget,
        settings.stream_max_tracks,
        settings.track_idle_s,
        min(settings.max_temporal_poses, settings.queue_size),  # a larger request could never be queued
    )
