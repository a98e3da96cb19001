"""Keypoint formats of 2D detectors and their declarative mapping onto the model's 17 joints."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float32]
BoolArray = npt.NDArray[np.bool_]

# The model's joint order (Human3.6M 17): the ONNX `joint_names` metadata repeats it.
MODEL_JOINTS: tuple[str, ...] = (
    "pelvis", "right_hip", "right_knee", "right_ankle", "left_hip", "left_knee", "left_ankle",
    "spine", "thorax", "neck", "head", "left_shoulder", "left_elbow", "left_wrist",
    "right_shoulder", "right_elbow", "right_wrist",
)  # fmt: skip
# Parent of each model joint (-1: the root), as in the ONNX `parents` metadata.
MODEL_PARENTS: tuple[int, ...] = (-1, 0, 1, 2, 0, 4, 5, 0, 7, 8, 9, 8, 11, 12, 8, 14, 15)


@dataclass(frozen=True)
class KeypointFormat:
    """A detector's joint list and, for each model joint, the source joints that give it."""

    name: str  # "h36m17", "mpii16", "coco17", "body25", "mediapipe33"
    joint_names: tuple[str, ...]  # source joints, in the detector's order
    # For each of the 17 model joints: () none (imputed by the model), (i,) a joint,
    # (i, k) the midpoint of two joints.
    sources: tuple[tuple[int, ...], ...]
    description: str = ""

    def __post_init__(self) -> None:
        if len(self.sources) != len(MODEL_JOINTS):
            raise ValueError(f"{self.name}: expected {len(MODEL_JOINTS)} sources, got {len(self.sources)}")
        for src in self.sources:
            if len(src) > 2 or any(not 0 <= i < len(self.joint_names) for i in src):
                raise ValueError(f"{self.name}: bad source {src} for {len(self.joint_names)} joints")


def _table(joint_names: tuple[str, ...], spec: dict[str, tuple[str, ...]]) -> tuple[tuple[int, ...], ...]:
    """Turn {model joint: source joint names} into index tuples in model joint order."""
    if unknown := set(spec) - set(MODEL_JOINTS):
        raise ValueError(f"unknown model joints {sorted(unknown)}")
    index = {name: i for i, name in enumerate(joint_names)}
    return tuple(tuple(index[s] for s in spec.get(joint, ())) for joint in MODEL_JOINTS)


def _format(
    name: str, description: str, joint_names: tuple[str, ...], spec: dict[str, tuple[str, ...]]
) -> KeypointFormat:
    return KeypointFormat(name, joint_names, _table(joint_names, spec), description)


# Human3.6M 'neck' (9) is the neck/nose joint and 'head' (10) the top of the head; detectors that
# only see the face map their nose onto 9 and have no head top, so 10 is imputed. No detector has
# the mid-torso 'spine' (7): it is imputed too, as in 3d-pose-baseline's Stacked-Hourglass inputs.
_LIMBS = {
    "right_hip": ("right_hip",), "right_knee": ("right_knee",), "right_ankle": ("right_ankle",),
    "left_hip": ("left_hip",), "left_knee": ("left_knee",), "left_ankle": ("left_ankle",),
    "left_shoulder": ("left_shoulder",), "left_elbow": ("left_elbow",), "left_wrist": ("left_wrist",),
    "right_shoulder": ("right_shoulder",), "right_elbow": ("right_elbow",),
    "right_wrist": ("right_wrist",),
}  # fmt: skip

H36M17 = _format(
    "h36m17",
    "Human3.6M 17 joints, the model's own order",
    MODEL_JOINTS,
    {joint: (joint,) for joint in MODEL_JOINTS},
)

MPII16 = _format(
    "mpii16", "MPII 16 joints (Stacked Hourglass and other MPII-trained detectors)",
    ("right_ankle", "right_knee", "right_hip", "left_hip", "left_knee", "left_ankle", "pelvis",
     "thorax", "upper_neck", "head_top", "right_wrist", "right_elbow", "right_shoulder",
     "left_shoulder", "left_elbow", "left_wrist"),
    {**_LIMBS, "pelvis": ("pelvis",), "thorax": ("thorax",), "neck": ("upper_neck",),
     "head": ("head_top",)},
)  # fmt: skip

COCO17 = _format(
    "coco17", "COCO 17 keypoints (YOLO-pose, RTMPose, Detectron2, MMPose, ViTPose)",
    ("nose", "left_eye", "right_eye", "left_ear", "right_ear", "left_shoulder", "right_shoulder",
     "left_elbow", "right_elbow", "left_wrist", "right_wrist", "left_hip", "right_hip",
     "left_knee", "right_knee", "left_ankle", "right_ankle"),
    {**_LIMBS, "pelvis": ("left_hip", "right_hip"), "thorax": ("left_shoulder", "right_shoulder"),
     "neck": ("nose",)},
)  # fmt: skip

# OpenPose's Neck and MidHip are detector outputs (trained as the shoulder and hip midpoints).
BODY25 = _format(
    "body25", "OpenPose BODY_25",
    ("nose", "neck", "right_shoulder", "right_elbow", "right_wrist", "left_shoulder",
     "left_elbow", "left_wrist", "mid_hip", "right_hip", "right_knee", "right_ankle", "left_hip",
     "left_knee", "left_ankle", "right_eye", "left_eye", "right_ear", "left_ear",
     "left_big_toe", "left_small_toe", "left_heel", "right_big_toe", "right_small_toe",
     "right_heel"),
    {**_LIMBS, "pelvis": ("mid_hip",), "thorax": ("neck",), "neck": ("nose",)},
)  # fmt: skip

MEDIAPIPE33 = _format(
    "mediapipe33", "MediaPipe Pose / BlazePose 33 landmarks (x, y in pixels)",
    ("nose", "left_eye_inner", "left_eye", "left_eye_outer", "right_eye_inner", "right_eye",
     "right_eye_outer", "left_ear", "right_ear", "mouth_left", "mouth_right", "left_shoulder",
     "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist", "left_pinky",
     "right_pinky", "left_index", "right_index", "left_thumb", "right_thumb", "left_hip",
     "right_hip", "left_knee", "right_knee", "left_ankle", "right_ankle", "left_heel",
     "right_heel", "left_foot_index", "right_foot_index"),
    {**_LIMBS, "pelvis": ("left_hip", "right_hip"), "thorax": ("left_shoulder", "right_shoulder"),
     "neck": ("nose",)},
)  # fmt: skip

FORMATS: dict[str, KeypointFormat] = {f.name: f for f in (H36M17, MPII16, COCO17, BODY25, MEDIAPIPE33)}
FORMAT_NAMES: tuple[str, ...] = tuple(FORMATS)  # ModelInput.format_index points into this

# COCO's nose, shoulders and hips; Human3.6M has its pelvis, knee, ankle, shoulder and elbow there.
_NOSE = COCO17.joint_names.index("nose")
_SHOULDERS = [COCO17.joint_names.index(j) for j in ("left_shoulder", "right_shoulder")]
_HIPS = [COCO17.joint_names.index(j) for j in ("left_hip", "right_hip")]


@cache
def lookalike_of(name: str) -> str | None:
    """The other format a pose in `name` is mistaken for: the one with as many joints, if any."""
    count = len(FORMATS[name].joint_names)
    others = [f for f in FORMATS if f != name and len(FORMATS[f].joint_names) == count]
    return others[0] if len(others) == 1 else None


def nose_height(points: np.ndarray, visible: np.ndarray) -> npt.NDArray[np.float32]:
    """How far joint 0 of (n, 17, 2) points lies beyond the shoulders (5, 6), in torso lengths
    (from the hips 11, 12) along the torso: (n,), NaN where a joint is missing or the torso has no
    length. Read as coco17, joint 0 is the nose, above the shoulders (typically +0.3); read as
    h36m17, those joints are the pelvis, left knee and ankle, left shoulder and elbow, and joint 0
    lies below "the shoulders" (typically -0.6). It uses the body's own axis, not the image's; the
    reply's format mix-up warning reads it (service.lookalike)."""
    # Missing joints may hold NaN or huge values: their results are replaced by NaN, never read.
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        shoulders = points[:, _SHOULDERS].mean(axis=1)  # (n, 2)
        axis = shoulders - points[:, _HIPS].mean(axis=1)  # (n, 2)
        length = (axis**2).sum(axis=1)  # (n,)
        height = ((points[:, _NOSE] - shoulders) * axis).sum(axis=1) / length
    ok = visible[:, [_NOSE, *_SHOULDERS, *_HIPS]].all(axis=1) & (length > 0)
    return np.where(ok, height, np.nan).astype(np.float32)


def _check_points(fmt: KeypointFormat, points: np.ndarray, visible: np.ndarray, num: int) -> None:
    if points.ndim != 3 or points.shape[1:] != (num, 2):
        raise ValueError(f"expected {fmt.name} points of shape (N, {num}, 2), got {points.shape}")
    if visible.shape != points.shape[:2]:
        raise ValueError(f"expected visible of shape {points.shape[:2]}, got {visible.shape}")


@cache
def _gather(fmt: KeypointFormat) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per model joint: first and second source index (equal for one source), has a source, is a midpoint."""
    first = np.array([src[0] if src else 0 for src in fmt.sources])
    second = np.array([src[-1] if src else 0 for src in fmt.sources])
    has_source = np.array([bool(src) for src in fmt.sources])
    midpoint = np.array([len(src) == 2 for src in fmt.sources])
    return first, second, has_source, midpoint


def to_model_joints(
    fmt: KeypointFormat, points: np.ndarray, visible: np.ndarray
) -> tuple[FloatArray, BoolArray, BoolArray, BoolArray]:
    """Map a detector's keypoints onto the model's joints.

    points (N, K, 2) pixels, visible (N, K) bool -> points (N, 17, 2) float32, visible (N, 17),
    derived (N, 17: the joint is a midpoint), imputed (N, 17: no visible source, the model fills
    it in). A derived joint is visible only if all its sources are; joints that are not visible
    get coordinates 0 so the model input stays finite.
    """
    _check_points(fmt, points, visible, len(fmt.joint_names))
    first, second, has_source, midpoint = _gather(fmt)
    src_visible = visible.astype(bool)
    out_visible = src_visible[:, first] & src_visible[:, second] & has_source  # (N, 17)
    # Missing joints may hold NaN or inf: their sums are replaced by 0, never read. The sum is taken
    # in the wire's precision (float32 from gRPC stays float32) and cast to float32 once.
    with np.errstate(invalid="ignore", over="ignore"):
        pairs = points[:, first] + points[:, second]  # (N, 17, 2); a single source: 2 p
        out = np.where(out_visible[..., None], pairs / 2, 0.0).astype(np.float32, copy=False)  # (N, 17, 2)
    derived = np.broadcast_to(midpoint, out_visible.shape).copy()
    return out, out_visible, derived, ~out_visible


def from_model_joints(
    fmt: KeypointFormat, points17: np.ndarray, visible17: np.ndarray | None = None
) -> tuple[FloatArray, BoolArray]:
    """Build a detector's keypoints from the model's 17 joints (for tests and evaluation).

    points17 (N, 17, 2) -> points (N, K, 2) float32, visible (N, K). A source joint is filled
    only when a model joint maps to it alone; joints the model has no counterpart for (eyes,
    ears, toes) are NaN and not visible.
    """
    if visible17 is None:
        visible17 = np.ones(points17.shape[:2], dtype=bool)
    _check_points(H36M17, points17, visible17, len(MODEL_JOINTS))
    n = points17.shape[0]
    out = np.full((n, len(fmt.joint_names), 2), np.nan, dtype=np.float32)  # (N, K, 2)
    out_visible = np.zeros((n, len(fmt.joint_names)), dtype=bool)
    for j, src in enumerate(fmt.sources):
        if len(src) == 1:
            ok = visible17[:, j].astype(bool)
            out[ok, src[0]] = points17[ok, j]
            out_visible[:, src[0]] = ok
    return out, out_visible


def describe_source(fmt: KeypointFormat, joint: int) -> str:
    """One model joint's source in words: a joint name, mid(a, b), or '— (imputed)'."""
    src = fmt.sources[joint]
    names = [fmt.joint_names[i] for i in src]
    if not names:
        return "— (imputed)"
    return names[0] if len(names) == 1 else f"mid({', '.join(names)})"


def format_table() -> str:
    """The mapping of every format as a Markdown table, one row per model joint."""
    fmts = list(FORMATS.values())
    lines = [
        "| # | model joint | " + " | ".join(f.name for f in fmts) + " |",
        "|---|---|" + "---|" * len(fmts),
    ]
    for j, joint in enumerate(MODEL_JOINTS):
        cells = " | ".join(describe_source(f, j) for f in fmts)
        lines.append(f"| {j} | {joint} | {cells} |")
    counts = " | ".join(str(len(f.joint_names)) for f in fmts)
    lines.append(f"| | input joints | {counts} |")
    return "\n".join(lines)


# Names users give formats, lower-cased without separators -> the format's own name.
FORMAT_ALIASES: dict[str, str] = {
    "openpose": "body25", "openposebody25": "body25", "op25": "body25",
    "coco": "coco17", "yolo": "coco17", "yolopose": "coco17", "yolov8": "coco17", "mmpose": "coco17",
    "detectron2": "coco17", "rtmpose": "coco17", "vitpose": "coco17", "cocowholebody": "coco17",
    "mediapipe": "mediapipe33", "blazepose": "mediapipe33", "mediapipepose": "mediapipe33",
    "mpii": "mpii16", "stackedhourglass": "mpii16", "hourglass": "mpii16",
    "h36m": "h36m17", "human36m": "h36m17", "human3.6m": "h36m17", "h3.6m": "h36m17",
}  # fmt: skip


def alias_of(name: str) -> str | None:
    """The format a name users give means ("openpose" -> body25, "BODY_25" -> body25), if any."""
    key = "".join(c for c in name.lower() if c.isalnum() or c == ".")
    if key in FORMATS:
        return key
    return FORMAT_ALIASES.get(key) or FORMAT_ALIASES.get(key.replace(".", ""))


def suggest_format(points: np.ndarray, present: np.ndarray) -> str | None:
    """The format a pose of (K, 2) points (present (K,): the joints given) looks like: the one format
    with K joints; where two have K (h36m17 and coco17), the one joint 0's height above the
    shoulders points to (nose_height: above, COCO's nose; below, Human3.6M's pelvis); else None."""
    names = [f.name for f in FORMATS.values() if len(f.joint_names) == len(points)]
    if len(names) < 2:
        return names[0] if names else None
    if len(points) != len(COCO17.joint_names):
        return None
    ok = present & np.isfinite(points).all(axis=-1)
    height = float(nose_height(np.asarray(points, np.float64)[None], ok[None])[0])
    if np.isnan(height):
        return None
    return COCO17.name if height > 0 else H36M17.name


def hint_for(points: np.ndarray, present: np.ndarray, given: str | None) -> str:
    """A hint for a pose that does not fit its format `given` (None: no format was sent): "; this
    looks like body25 (OpenPose BODY_25): send format \"body25\"", or "" when nothing fits better."""
    found = suggest_format(points, present)
    if found is None or found == given:
        return ""
    described = FORMATS[found].description
    return f'; {len(points)} joints: this looks like {found} ({described}): send format "{found}"'


def raw_output_hint(data: object) -> str | None:
    """What to do with a detector's own output file posted as a POST /lift body, or None for any
    other body: an OpenPose --write_json frame ({"version", "people": [{"pose_keypoints_2d"}]}) or
    COCO keypoint results / annotations ([{"image_id", "keypoints": [x, y, s, ...]}])."""
    if isinstance(data, dict) and "people" in data and "poses" not in data:
        return (
            "this is OpenPose output (--write_json): use `repnet lift` on the file or folder, or send "
            'each person\'s pose_keypoints_2d as {"keypoints": [[x, y, c], ...]} with format "body25"'
        )
    items = data.get("annotations") if isinstance(data, dict) and "poses" not in data else data
    first = items[0] if isinstance(items, list) and items else None
    if isinstance(first, dict) and "keypoints" in first and ("image_id" in first or "category_id" in first):
        return (
            "this is COCO keypoint output ([{image_id, keypoints: [x, y, score, ...]}]): use `repnet lift` "
            'on the file, or send each result\'s keypoints as {"keypoints": [[x, y, score], ...]} with '
            'format "coco17"'
        )
    return None
