"""Pydantic request and response models of the HTTP API; their descriptions are the OpenAPI docs."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    JsonValue,
    Strict,
    ValidationError,
    ValidatorFunctionWrapHandler,
    WrapValidator,
    field_validator,
    model_validator,
)
from pydantic_core import PydanticCustomError

from repnet.core.contract import MAX_FRAME, MAX_TRACK_ID
from repnet.core.errors import echo, encodable
from repnet.core.format_hints import raw_output_hint
from repnet.core.formats import DEFAULT_FORMAT, FORMATS
from repnet.core.inputs import EXAMPLE_KEYPOINTS
from repnet.core.report import MAX_POSE_ERRORS, REPORT

# Strict: a JSON string such as "12" or a boolean is not a coordinate.
Number = Annotated[float, Strict()]
# One joint: [x, y]; [x, y, confidence] (OpenPose, MMPose, YOLO-pose); MediaPipe's [x, y, z,
# visibility]. A list, not a union of tuples: pydantic would name each union member in its errors.
Row = Annotated[list[Number], Field(min_length=2, max_length=4)]
Size = tuple[Annotated[float, Strict(), Field(gt=0)], Annotated[float, Strict(), Field(gt=0)]]
ROW_LAYOUTS = "[x, y], [x, y, confidence] or MediaPipe [x, y, z, visibility]"
Matrix = list[list[float]]
Finite = Annotated[float, Strict(), Field(allow_inf_nan=False)]
PositiveFinite = Annotated[float, Strict(), Field(gt=0, allow_inf_nan=False)]

FRAME_DOC = (
    "Coordinate contract: `pose_3d` is in millimetres with the pelvis at the origin, in the model's "
    "template frame (x to the subject's image right, y down, z away from the camera, the subject "
    "facing the camera). `pose_3d_camera` is the same pose rotated into the camera's orientation "
    "(`pose_3d @ rotation.T`). `camera` K is a weak-perspective 2x3 matrix: K @ pose_3d.T equals "
    "the input normalised (centred on the mean of its visible joints, divided by the standard "
    "deviation of their coordinates) up to a translation. `reprojection` maps K @ pose_3d back "
    "into input pixels (x right, y down)."
)


UNKNOWN_FIELD = "unknown_field"  # pydantic error type of reject_unknown_keys
DETECTOR_OUTPUT = "detector_output"  # pydantic error type of a detector's own file posted as a body


def reject_unknown_keys(model: type[BaseModel], data: Any) -> None:
    """All unknown keys of one object as one error naming the first (cut short) and counting the
    rest: pydantic's extra="forbid" gives one error per key, and echoes each key in full. The
    error's context `key` is the first unknown key, which the adapter appends to the field."""
    if not isinstance(data, dict):
        return
    unknown = [key for key in data if key not in model.model_fields]
    if unknown:
        more = f" (and {len(unknown) - 1} more unknown fields)" if len(unknown) > 1 else ""
        raise PydanticCustomError(
            UNKNOWN_FIELD,
            "unknown field {name} is not permitted{more}; expected one of {expected}",
            {
                "key": encodable(str(unknown[0])),
                "name": echo(str(unknown[0])),
                "more": more,
                "expected": ", ".join(model.model_fields),
            },
        )


# Lists of the request stop at their first invalid item (fail_fast): a list of 300,000 wrong
# values gets one error, found in microseconds, instead of 300,000 errors built over seconds.


class CameraIntrinsics(BaseModel):
    """The pinhole camera that took the image, in pixels (as in its calibration or EXIF focal length)."""

    model_config = ConfigDict(extra="forbid")

    focal_px: tuple[PositiveFinite, PositiveFinite] = Field(
        description="[fx, fy] focal lengths in pixels.", examples=[[1145.0, 1144.0]]
    )
    principal_point_px: tuple[Finite, Finite] = Field(
        description="[cx, cy] principal point in pixels (usually near the image centre).",
        examples=[[512.0, 515.0]],
    )

    @model_validator(mode="before")
    @classmethod
    def _check_keys(cls, data: Any) -> Any:
        reject_unknown_keys(cls, data)
        return data


INTRINSICS_DOC = (
    "The camera's intrinsics, if known. `pose_3d_camera` is then turned along the ray from the camera "
    "to the person as well: the model sees each pose centred, as if it stood on the optical axis, "
    "and without the intrinsics its camera-frame orientation misses the off-axis angle (on Human3.6M "
    "S9/S11 the bundled model's P-I is 55.6 mm with them and 70.2 mm without, docs/RESULTS.md)."
)

HEIGHT_DOC = (
    "The person's skeleton height in metres, in [0.5, 2.5]: head top to ankle along the bones (about "
    "stature minus 0.1 m). With `intrinsics`, `root_camera_m` takes its depth from it; without it, "
    "from the answer's own (template) size (`root_height_source`)."
)


class PoseIn(BaseModel):
    """One 2D pose from a detector."""

    model_config = ConfigDict(extra="forbid")

    keypoints: list[Row | None] = Field(
        description="One row per joint of the format, in the format's joint order; null for a "
        "joint the detector did not find. Every row is [x, y] in pixels (x right, y down), or "
        "[x, y, confidence] as most detectors write them (then leave `confidence` out), or "
        "MediaPipe's normalised [x, y, z, visibility] (format mediapipe33, with `image_size`; z is "
        "ignored, visibility is the confidence).",
        examples=[[[512.0, 400.0], None]],
        fail_fast=True,
    )
    confidence: list[Number] | None = Field(
        None,
        description="Optional detector confidence per joint in [0, 1]; a joint below the "
        "confidence threshold counts as missing.",
        fail_fast=True,
    )
    format: str | None = Field(
        None,
        description="Keypoint format of this pose; defaults to the request's `format`.",
        json_schema_extra={"enum": list(FORMATS)},
    )
    image_size: Size | None = Field(
        None,
        description="[width, height] of the image in pixels when x and y are normalised to [0, 1] "
        "(MediaPipe): they are multiplied by it. Defaults to the request's `image_size`.",
    )
    intrinsics: CameraIntrinsics | None = Field(
        None, description=INTRINSICS_DOC + " Defaults to the request's `intrinsics`."
    )
    person_height_m: Number | None = Field(None, description=HEIGHT_DOC + " Defaults to the request's.")
    track_id: Annotated[str, Strict(), Field(min_length=1, max_length=MAX_TRACK_ID)] | None = Field(
        None,
        description="The person this pose belongs to: with `temporal` causal or offline, the poses of one "
        "track_id are one person's clip, ordered by `frame`. Echoed in the reply.",
    )
    frame: Annotated[int, Strict(), Field(ge=0, le=MAX_FRAME)] | None = Field(
        None,
        description="The pose's frame number in its track (needed with `track_id` and `temporal`): "
        "frames are 1 / fps apart; a gap of up to 0.5 s is bridged, a longer one starts the track again. "
        f"At most {MAX_FRAME} (2^53 - 1).",
    )

    @model_validator(mode="before")
    @classmethod
    def _check_keys(cls, data: Any) -> Any:
        reject_unknown_keys(cls, data)
        return data

    @field_validator("keypoints", mode="before")
    @classmethod
    def _check_rows(cls, value: Any) -> Any:
        """A wrongly shaped array is one error, not one per joint: a flat list [x0, y0, x1, ...]
        (the gRPC layout), a list of poses, or rows of another or of mixed lengths."""
        if not isinstance(value, list) or not value:
            return value
        if type(value[0]) in (int, float):
            raise PydanticCustomError(
                "keypoints_shape",
                "expected one row per joint ({layouts}, null for a missing joint), "
                "got a flat list of {count} numbers",
                {"count": len(value), "layouts": ROW_LAYOUTS},
            )
        if type(value[0]) is list and value[0] and type(value[0][0]) is list:
            raise PydanticCustomError(
                "keypoints_shape",
                "expected the rows of one pose, got a list of {count} poses: send a batch as {batch}",
                {"count": len(value), "batch": '{"poses": [{"keypoints": ...}, ...]}'},
            )
        lengths = {len(row) for row in value if type(row) is list}
        if len(lengths) > 1 or not lengths <= {2, 3, 4}:
            raise PydanticCustomError(
                "keypoints_shape",
                "expected every row to be {layouts} (null for a missing joint), got rows of {lengths} values",
                {"layouts": ROW_LAYOUTS, "lengths": " and ".join(map(str, sorted(lengths)))},
            )
        return value

    @property
    def refusal(self) -> list[dict[str, Any]]:
        """Why the request's schema refused this pose (PoseRefused); [] for a valid pose."""
        return []


class PoseRefused(PoseIn):
    """A pose of an `invalid_poses: report` request that PoseIn refused: made by LiftRequest's
    validator (never from JSON), it holds pydantic's errors, located within the pose."""

    errors: list[dict[str, Any]] = Field(default_factory=list, exclude=True)

    @property
    def refusal(self) -> list[dict[str, Any]]:
        """Why the request's schema refused this pose."""
        return self.errors


def _each_pose(value: Any) -> Any:
    """A pose already validated or refused by LiftRequest's validator (report), else the JSON value."""
    if isinstance(value, list):
        return [p if isinstance(p, PoseIn) else _one_pose(p) for p in value]
    return value


def _one_pose(value: Any) -> PoseIn:
    try:
        return PoseIn.model_validate(value)
    except ValidationError as err:
        return PoseRefused.model_construct(keypoints=[], errors=err.errors(include_url=False))


def _pass_validated(value: Any, handler: ValidatorFunctionWrapHandler) -> Any:
    return value if isinstance(value, PoseIn) else handler(value)


INVALID_POSES_DOC = (
    "What to do with poses that break an input rule: `refuse` (default) answers 422 for the whole "
    "request, naming every such pose; `report` lifts the others and answers 200 with `null` in "
    "`poses` for each pose not lifted and its errors in `errors` (each with its `pose` index; at most "
    f"{MAX_POSE_ERRORS} per pose, `error_count` counts them all). The request's own rules (pose count, "
    "threshold, a temporal request's tracks and fps) refuse it whole either way."
)


# A person in mid-stride seen from 4.5 m (h36m17 joint order, px): the OpenAPI example request.


EXAMPLE: list[JsonValue] = [list(p) for p in EXAMPLE_KEYPOINTS]  # the example person, as JSON


class LiftRequest(BaseModel):
    """A batch of poses. A bare pose object ({"keypoints": ...}) is accepted as a batch of one."""

    model_config = ConfigDict(
        extra="forbid",
        json_schema_extra={"examples": [{"poses": [{"keypoints": EXAMPLE}], "format": DEFAULT_FORMAT}]},
    )

    poses: list[Annotated[PoseIn, WrapValidator(_pass_validated)]] = Field(
        description="The poses to lift, answered in the same order.", fail_fast=True
    )
    format: str = Field(
        "h36m17",
        description="Keypoint format of poses that do not name their own: " + ", ".join(FORMATS) + ".",
        json_schema_extra={"enum": list(FORMATS)},
    )
    confidence_threshold: Number | None = Field(
        None, description="Joints with a confidence below this count as missing (default: server setting)."
    )
    image_size: Size | None = Field(
        None, description="`image_size` of poses that do not give their own ([width, height] in pixels)."
    )
    intrinsics: CameraIntrinsics | None = Field(
        None, description="`intrinsics` of poses that do not give their own. " + INTRINSICS_DOC
    )
    person_height_m: Number | None = Field(
        None, description="`person_height_m` of poses that do not give their own. " + HEIGHT_DOC
    )
    temporal: Literal["off", "causal", "offline"] = Field(
        "off",
        description="How tracked poses (with `track_id` and `frame`) are lifted: off, each alone; causal, "
        "each from its track's frames up to it (as a LiftStream answers them); offline, each from the "
        "frames around it in its whole track. Untracked poses are always lifted alone.",
    )
    fps: Annotated[float, Strict()] | None = Field(
        None, description="Frames per second of the tracks, in (0, 240]; needed with `temporal`."
    )
    invalid_poses: Literal["refuse", "report"] = Field("refuse", description=INVALID_POSES_DOC)
    model: str | None = Field(
        None,
        description="The model to lift with: a `model_id` that GET /v1/models lists (default: the "
        "service's default model). An unknown one is a 422 naming the known ones; `temporal` causal "
        "or offline runs over the model the temporal models were trained on only.",
    )

    @model_validator(mode="before")
    @classmethod
    def _accept_single_pose(cls, data: Any) -> Any:
        if (hint := raw_output_hint(data)) is not None:
            raise PydanticCustomError(DETECTOR_OUTPUT, hint)
        if isinstance(data, dict) and "poses" not in data and "keypoints" in data:
            request_level = ("confidence_threshold", "model", "invalid_poses")
            batch = {"poses": [{k: v for k, v in data.items() if k not in request_level}]}
            batch.update({k: data[k] for k in request_level if k in data})
            return batch
        reject_unknown_keys(cls, data)
        if isinstance(data, dict) and data.get("invalid_poses") == REPORT:  # each pose on its own
            return {**data, "poses": _each_pose(data.get("poses"))}
        return data
