"""What GET /v1/model says: the model, its joints and formats, the limits, its public metadata."""

from __future__ import annotations

from service.engine import Engine
from service.formats import FORMATS
from service.keypoints import Limits
from service.lifter import ModelInfo
from service.schemas import FormatInfo, LimitsInfo, ModelDescription


def describe_model(info: ModelInfo, limits: Limits, engine: Engine, max_body_bytes: int) -> ModelDescription:
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
            max_wait_ms=engine.max_wait_s * 1000,
            queue_size=engine.queue_size,
        ),
        plausibility=engine.lifter.has_plausibility,
        plausibility_calibration=info.plausibility_calibration,
        evaluation=info.evaluation,
        metadata=info.public_metadata,
    )
