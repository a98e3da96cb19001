"""Hints about keypoint formats: which format a pose's joints look like, the names people use for a
format, the table the CLI prints, and what a detector's own file looks like when posted as is."""

from __future__ import annotations

from functools import cache

import numpy as np
import numpy.typing as npt

from repnet.core.file_hints import detector_file_hint
from repnet.core.formats import COCO17, FORMATS, H36M17, MODEL_JOINTS, KeypointFormat

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
    reply's format mix-up warning reads it (repnet.core.lookalike)."""
    # Missing joints may hold NaN or huge values: their results are replaced by NaN, never read.
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        shoulders = points[:, _SHOULDERS].mean(axis=1)  # (n, 2)
        axis = shoulders - points[:, _HIPS].mean(axis=1)  # (n, 2)
        length = (axis**2).sum(axis=1)  # (n,)
        height = ((points[:, _NOSE] - shoulders) * axis).sum(axis=1) / length
    ok = visible[:, [_NOSE, *_SHOULDERS, *_HIPS]].all(axis=1) & (length > 0)
    return np.where(ok, height, np.nan).astype(np.float32)


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
    "openpose": "body25",
    "openposebody25": "body25",
    "op25": "body25",
    "coco": "coco17",
    "yolo": "coco17",
    "yolopose": "coco17",
    "yolov8": "coco17",
    "mmpose": "coco17",
    "detectron2": "coco17",
    "rtmpose": "coco17",
    "vitpose": "coco17",
    "cocowholebody": "coco17",
    "mediapipe": "mediapipe33",
    "blazepose": "mediapipe33",
    "mediapipepose": "mediapipe33",
    "mpii": "mpii16",
    "stackedhourglass": "mpii16",
    "hourglass": "mpii16",
    "h36m": "h36m17",
    "human36m": "h36m17",
    "human3.6m": "h36m17",
    "h3.6m": "h36m17",
}


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
    COCO keypoint results / annotations ([{"image_id", "keypoints": [x, y, s, ...]}]), or one of
    the files core.file_hints knows (MMPose, YOLO, MediaPipe, AlphaPose, COCO-WholeBody)."""
    if (hint := detector_file_hint(data)) is not None:
        return hint
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
