"""The reply's fields, declared once: each field of a pose's answer with its per-pose shape, kind and
meaning. The HTTP schema (server.http.schemas.PoseResult) is built from this table, the client's
result (client.result.LiftResult) reads its shapes from it, the replies are computed in its order
(runtime.replies), and tests/service/test_replies.py holds the proto's PoseResult to it."""

from __future__ import annotations

from dataclasses import dataclass

ANY = -1  # in a per-pose shape: one per model joint, or a list of any length

PLAUSIBILITY_DOC = (
    "How plausible the 3D pose is, in [0, 1]: the model's pose score (the bundled model's: a density "
    "over real people's bone directions and proportions) calibrated as a percentile among real "
    "validation poses (0.3: more plausible than 30 % of them; near 0: a pose unlike any real one). "
    "It judges the 3D pose alone, not its fit to the input (that is "
    "`reprojection_error_px`). null when the loaded model has no plausibility output."
)


@dataclass(frozen=True)
class ReplyField:
    """One field of a pose's reply, under the same name in JSON, proto, the pydantic schema and the client."""

    name: str
    shape: tuple[int, ...]  # per pose: () a scalar, ANY one per model joint (or any number of strings)
    kind: type  # float, bool or str
    doc: str  # what it means, with its units (the HTTP schema's description)
    optional: bool = False  # absent for some poses or models: null in JSON, unset in proto
    choices: tuple[str, ...] = ()  # the values a str field takes, where they are few


# Every field of a pose's reply, in reply order.
FIELDS: tuple[ReplyField, ...] = (
    ReplyField("pose_3d", (ANY, 3), float, "17 x [x, y, z] in mm, pelvis at origin, template frame."),
    ReplyField(
        "pose_3d_camera",
        (ANY, 3),
        float,
        "17 x [x, y, z] in mm: pose_3d rotated into the camera's orientation (pose_3d @ rotation.T); with "
        "`intrinsics`, then also turned along the ray from the camera to the person "
        "(pose_3d @ (ray @ rotation).T).",
    ),
    ReplyField("camera", (2, 3), float, "Weak-perspective camera K, 2 x 3."),
    ReplyField("scale", (), float, "Camera scale s = sqrt(trace(K K^T) / 2)."),
    ReplyField(
        "rotation",
        (3, 3),
        float,
        "Camera rotation R, 3 x 3 orthonormal with det 1: rows 1-2 are K / s made orthonormal, row 3 "
        "their cross product.",
    ),
    ReplyField("reprojection", (ANY, 2), float, "17 x [x, y]: K @ pose_3d mapped back into input pixels."),
    ReplyField(
        "reprojection_error_px",
        (),
        float,
        "Mean distance in pixels between `reprojection` and the input over the visible joints.",
    ),
    ReplyField("visible", (ANY,), bool, "Per joint: the model saw this joint."),
    ReplyField(
        "imputed", (ANY,), bool, "Per joint: the input had no visible source for it; the model filled it in."
    ),
    ReplyField(
        "derived",
        (ANY,),
        bool,
        "Per joint: the input point is the midpoint of two detector joints (pelvis = mid-hips for COCO).",
    ),
    ReplyField("plausibility", (), float, PLAUSIBILITY_DOC, optional=True),
    ReplyField(
        "warnings",
        (ANY,),
        str,
        "Why this answer may be wrong although the input was accepted: that the keypoints look like "
        'another format with as many joints ("format: these keypoints look like coco17, not h36m17 ..."), '
        "that joints at exactly (0, 0) were read as missing, or that the 3D pose looks implausible "
        '(plausibility below 0.01: "plausibility: the 3D pose looks implausible ..."). Empty when nothing '
        "looks wrong.",
    ),
    ReplyField(
        "temporal",
        (),
        bool,
        "A temporal model answered this tracked pose: `pose_3d_camera` is its answer, with the track's bone "
        "lengths, and `pose_3d` that pose turned back by `rotation`.",
    ),
    ReplyField("track_id", (), str, "The pose's `track_id`, null for an untracked pose.", optional=True),
    ReplyField(
        "root_camera_m",
        (3,),
        float,
        "[x, y, z] of the root (pelvis) in the camera frame, metres (x right, y down, z forward); null "
        "without `intrinsics`. The answer, at the person's size, placed where it reprojects best onto "
        "the input through the camera: a trajectory over a clip.",
        optional=True,
    ),
    ReplyField(
        "root_height_source",
        (),
        str,
        'Whose size set `root_camera_m`\'s depth: "given" (`person_height_m`) or "template" (the answer\'s '
        "own size); null without `root_camera_m`.",
        optional=True,
        choices=("given", "template"),
    ),
)
NAMES: tuple[str, ...] = tuple(f.name for f in FIELDS)
# The per-pose float matrices (ANY: one row per model joint) and per-joint flags of a reply.
MATRICES: dict[str, tuple[int, ...]] = {
    f.name: f.shape for f in FIELDS if f.kind is float and len(f.shape) == 2
}
FLAGS: tuple[str, ...] = tuple(f.name for f in FIELDS if f.kind is bool and f.shape == (ANY,))
