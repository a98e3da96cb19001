"""What GET /v1/model and GET /v1/models say: their schemas (the model, its joints and formats,
the limits, the loaded temporal models' contracts, its public metadata; every model served with
its lineage) and how they are filled in."""

from __future__ import annotations

from typing import Any

from fastapi import FastAPI
from pydantic import BaseModel, Field

from repnet.core.contract import (
    DEFAULT_FPS,
    ENVELOPE_BYTES,
    MAX_FPS,
    MAX_FRAME,
    MAX_GAP_S,
    MAX_TRACK_ID,
    TEMPORAL_MODES,
)
from repnet.core.formats import DEFAULT_FORMAT, FORMATS
from repnet.core.inputs import Limits
from repnet.runtime.batchers import LiftBatcher
from repnet.runtime.catalog import Catalog
from repnet.runtime.lifter import ModelInfo
from repnet.runtime.plans import TemporalModels
from repnet.server.http.schemas import FRAME_DOC


class FormatInfo(BaseModel):
    """A keypoint format of GET /v1/model: its joints and how they map onto the model's."""

    name: str
    description: str
    joint_names: list[str] = Field(description="The format's joints in the detector's order.")
    sources: list[list[int]] = Field(
        description="Per model joint: the format joints it comes from (none: imputed; two: their midpoint)."
    )


class LimitsInfo(BaseModel):
    """The input limits and batching settings of GET /v1/model."""

    max_request_poses: int
    max_body_bytes: int
    min_visible_joints: int
    confidence_threshold: float
    max_coordinate_px: float
    max_batch: int
    max_wait_ms: float
    company_wait_ms: float = Field(
        0.0,
        description="The longest a request waits for a client expected to send within it "
        "(REPNET_COMPANY_WAIT_MS; docs/API.md, The batching window).",
    )
    queue_size: int
    max_temporal_poses: int | None = Field(
        None,
        description="Most poses in one request with `temporal` causal or offline "
        "(REPNET_MAX_TEMPORAL_POSES, at most queue_size); null when no temporal model is loaded.",
    )


class RulesInfo(BaseModel):
    """What a client needs to send tracked poses and long clips as the service takes them (the page
    reads them from here): the track rules and how clients cut a clip into requests."""

    temporal_modes: list[str] = Field(default=list(TEMPORAL_MODES), description="Values of `temporal`.")
    default_format: str = Field(default=DEFAULT_FORMAT, description="The format of a pose that names none.")
    max_gap_s: float = Field(
        default=MAX_GAP_S, description="The longest gap a track bridges, s; a longer one starts it again."
    )
    max_fps: float = Field(default=MAX_FPS, description="The highest frame rate a track may declare.")
    max_frame: int = Field(default=MAX_FRAME, description="The largest frame number of a tracked pose.")
    max_track_id_chars: int = Field(default=MAX_TRACK_ID, description="The longest track id.")
    assumed_fps: float = Field(
        default=DEFAULT_FPS, description="The frame rate clients assume for a sequence that gives none."
    )
    envelope_bytes: int = Field(
        default=ENVELOPE_BYTES, description="What clients keep free of a body's limit besides its poses."
    )


class TemporalModelInfo(BaseModel):
    """A loaded temporal model's contract (its ONNX metadata `temporal`): what a client needs to
    split a clip longer than one request into parts that are answered as the whole clip would be."""

    mode: str = Field(
        description="causal (the answer for a frame reads it and the frames before) "
        "or offline (a window centred on the frame)."
    )
    window: int = Field(description="T: the frames of one window on the model's time grid.")
    grid_fps: float = Field(
        description="The rate of the model's time grid: a window spans (window - 1) / grid_fps seconds."
    )
    max_fps: float = Field(
        description="Tracks faster than this are read every q-th frame, q = ceil(fps / max_fps)."
    )
    model_id: str


class ModelDescription(BaseModel):
    """What `GET /v1/model` returns."""

    model_id: str
    skeleton: str
    joints: list[str]
    parents: list[int]
    coordinate_contract: str = FRAME_DOC
    formats: list[FormatInfo]
    limits: LimitsInfo
    temporal: list[TemporalModelInfo] = Field(
        default_factory=list,
        description="The temporal models this service loaded (one per mode), for requests with "
        "`temporal` causal or offline; empty: tracked poses are lifted alone.",
    )
    training_method: str = Field(
        "",
        description="How the model was trained (the bundled one: supervised on synthetic projections of "
        "Human3.6M poses; the paper's adversarial losses are in `repnet adapt`); empty when unknown.",
    )
    rules: RulesInfo = Field(default_factory=lambda: RulesInfo(), description=RulesInfo.__doc__)
    plausibility: bool = Field(False, description="The model gives each pose a `plausibility`.")
    plausibility_calibration: dict[str, Any] | None = Field(
        None, description="How the plausibility was calibrated (ONNX metadata `plausibility_calibration`)."
    )
    evaluation: dict[str, Any] = Field(description="Evaluation figures embedded in the model.")
    metadata: dict[str, str] = Field(
        description="Every ONNX metadata entry, with paths of the machine that built the model cut "
        "to their runs/ folder or file name (runs/s5_r2_limbs/last.pt)."
    )


def temporal_models(temporal: TemporalModels | None) -> list[TemporalModelInfo]:
    """The contract of each loaded temporal model, causal first."""
    engines = {} if temporal is None else temporal.engines
    found = []
    for mode in sorted(engines):
        lifter = engines[mode].lifter
        c = lifter.contract
        found.append(
            TemporalModelInfo(
                mode=c.mode, window=c.window, grid_fps=c.grid_fps, max_fps=c.max_fps, model_id=lifter.model_id
            )
        )
    return found


def describe_model(
    info: ModelInfo,
    limits: Limits,
    engine: LiftBatcher,
    max_body_bytes: int,
    temporal: TemporalModels | None = None,
) -> ModelDescription:
    """What GET /v1/model says: the model, its joints and formats, the limits, its public metadata."""
    formats = [
        FormatInfo(
            name=f.name,
            description=f.description,
            joint_names=list(f.joint_names),
            sources=[list(s) for s in f.sources],
        )
        for f in FORMATS.values()
    ]
    return ModelDescription(
        model_id=info.model_id,
        skeleton=info.skeleton,
        joints=list(info.joint_names),
        parents=list(info.parents),
        formats=formats,
        limits=LimitsInfo(
            max_request_poses=limits.max_request_poses,
            max_body_bytes=max_body_bytes,
            min_visible_joints=limits.min_visible_joints,
            confidence_threshold=limits.confidence_threshold,
            max_coordinate_px=limits.max_coordinate,
            max_batch=engine.max_batch,
            max_wait_ms=engine.window.max_wait_s * 1000,
            company_wait_ms=engine.window.company_wait_s * 1000,
            queue_size=engine.queue_size,
            max_temporal_poses=None if temporal is None else temporal.max_poses,
        ),
        temporal=temporal_models(temporal),
        training_method=info.training_method,
        plausibility=engine.lifter.has_plausibility,
        plausibility_calibration=info.plausibility_calibration,
        evaluation=info.evaluation,
        metadata=info.public_metadata,
    )


class ModelSummary(BaseModel):
    """One model of GET /v1/models."""

    model_id: str = Field(description="The name a request gives in `model` to be lifted by it.")
    default: bool = Field(description="A request that names no model gets this one.")
    skeleton: str
    sha256: str = Field("", description="The model file's sha256 (what a derived model's lineage names).")
    temporal: bool = Field(
        description="Requests with `temporal` causal or offline (and tracked stream frames) may name "
        "it: the loaded temporal models were trained on its answers, or on those of the model it was "
        "adapted from (`repnet adapt`)."
    )
    temporal_models: list[str] = Field(
        default_factory=list,
        description="The model_id of each temporal model that runs over it (empty: none).",
    )
    plausibility: bool = Field(description="The model gives each pose a `plausibility`.")
    evaluation: dict[str, Any] = Field(description="Evaluation figures embedded in the model.")
    metadata: dict[str, str] = Field(
        description="Every ONNX metadata entry (its lineage: parent model, command, data hashes), "
        "with paths of the machine that built the model cut as in GET /v1/model."
    )


class ModelList(BaseModel):
    """What `GET /v1/models` returns."""

    default: str = Field(description="The model_id of the default model.")
    models: list[ModelSummary] = Field(description="Every model served, the default first.")


def describe_models(models: Catalog, temporal: TemporalModels | None = None) -> ModelList:
    """What GET /v1/models says: each model served, with its lineage and the temporal models that
    run over it, the default first."""
    temporal_ids = [] if temporal is None else [e.lifter.model_id for e in temporal.engines.values()]
    found = []
    for model_id, engine in models.engines.items():
        info = engine.lifter.info
        found.append(
            ModelSummary(
                model_id=model_id,
                default=model_id == models.default,
                skeleton=info.skeleton,
                sha256=models.sha256.get(model_id, ""),
                temporal=models.runs_temporal(model_id),
                temporal_models=temporal_ids if models.runs_temporal(model_id) else [],
                plausibility=engine.lifter.has_plausibility,
                evaluation=info.evaluation,
                metadata=info.public_metadata,
            )
        )
    return ModelList(default=models.default, models=found)


def add_model_routes(
    app: FastAPI,
    models: Catalog,
    limits: Limits,
    max_body_bytes: int,
    temporal: TemporalModels | None,
    errors: dict[int | str, dict[str, Any]],
) -> None:
    """GET /v1/model (the default model, or `?model=`) and GET /v1/models (every model)."""

    summary = "Model, joints, formats and limits"

    @app.get("/v1/model", response_model=ModelDescription, responses=errors, summary=summary)
    async def model(model: str | None = None) -> ModelDescription:
        """The default model, or the one `?model=` names (a model_id of GET /v1/models)."""
        chosen = models.pick(model)
        runs_temporal = models.runs_temporal(chosen.lifter.info.model_id)
        return describe_model(
            chosen.lifter.info, limits, chosen, max_body_bytes, temporal if runs_temporal else None
        )

    @app.get("/v1/models", response_model=ModelList, summary="Every model served, with its lineage")
    async def list_models() -> ModelList:
        """The models a request may name in `model`, the default first, each with its metadata."""
        return describe_models(models, temporal)
