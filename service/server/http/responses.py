"""Pydantic models of the HTTP API's answers: a lift's reply (its fields from core.fields) and an
error's body; their descriptions are the OpenAPI docs."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, Field, create_model

from repnet.core.fields import ANY, FIELDS, ReplyField
from repnet.core.report import MAX_POSE_ERRORS
from repnet.server.http.schemas import Matrix


def _result_type(field: ReplyField) -> tuple[Any, Any]:
    """The pydantic type and default of one reply field (core.fields)."""
    scalar: Any = Literal[field.choices] if field.choices else field.kind
    kind: Any = scalar if not field.shape else list[scalar] if len(field.shape) == 1 else Matrix
    if field.optional:
        return kind | None, Field(None, description=field.doc)
    if field.shape == (ANY,) and field.kind is str:  # a list: empty, never absent
        return kind, Field(default_factory=list, description=field.doc)
    return kind, Field(description=field.doc)


# The 3D pose and camera for one input pose: core.fields' fields, in their order.
_RESULT_FIELDS: dict[str, Any] = {f.name: _result_type(f) for f in FIELDS}
PoseResult: type[BaseModel] = create_model(
    "PoseResult",
    __doc__="The 3D pose and camera for one input pose. Joint arrays follow `joints` (17 model joints).",
    **_RESULT_FIELDS,
)


class ErrorItem(BaseModel):
    """One rejected field."""

    field: str = Field(description='Where, e.g. "poses[2].keypoints[5]".')
    reason: str = Field(description="Why it was rejected.")
    message: str = Field(description="Field, joint name and reason in one line (the gRPC message).")
    code: str = Field(description='Short reason code, e.g. "non_finite" (the metrics label).')
    pose: int | None = Field(None, description="Index of the pose in the request.")
    joint: int | None = Field(None, description="Index of the joint in the pose's format.")
    joint_name: str | None = Field(None, description="Name of the joint in the pose's format.")


LiftResponse: type[BaseModel] = create_model(
    "LiftResponse",
    __doc__="The lifted poses, in request order.",
    model_id=(str, Field(description="Id of the model that answered.")),
    joints=(list[str], Field(description="Names of the 17 model joints, the order of every joint array.")),
    poses=(
        list[PoseResult | None],  # type: ignore[valid-type]
        Field(
            description="One result per request pose, in request order; null for a pose not lifted "
            "(`invalid_poses: report` only)."
        ),
    ),
    errors=(
        list[ErrorItem] | None,
        Field(
            None,
            description="With `invalid_poses: report`: why each pose not lifted was not, naming it "
            f"(`pose`, `field`); at most {MAX_POSE_ERRORS} per pose. Absent otherwise.",
        ),
    ),
    error_count=(
        int | None,
        Field(None, description="With `invalid_poses: report`: every violation of the poses not lifted."),
    ),
)


class ErrorResponse(BaseModel):
    """A 4xx/503 answer: `detail` lists the rejected fields, or says why the server cannot serve."""

    detail: list[ErrorItem] | str
    error_count: int | None = Field(
        None, description="How many fields were rejected; `detail` lists the first 20 of them."
    )
