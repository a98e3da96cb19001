"""Hints about keypoint formats: which format a pose's joints look like, the names people use for a
format, the table the CLI prints, and what a detector's own file looks like when posted as is."""

from __future__ import annotations

from functools import cache

import numpy as np
import numpy.typing as npt

from repnet.core.file_hints import detector_file_hint
from repnet.core.formats import (
    BODY25,
    COCO17,
    FORMATS,
    H36M17,
    MODEL_JOINTS,
    OPENPOSE_FORMATS,
    KeypointFormat,
)

# COCO's nose, shoulders and hips; Human3.6M has its pelvis, knee, ankle, shoulder and elbow there.
_NOSE = COCO17.joint_names.index("nose")


_SHOULDERS = [COCO17.joint_names.index(j) for j in ("left_shoulder", "right_shoulder")]


_HIPS = [COCO17.joint_names.index(j) for j in ("left_hip", "right_hip")]


@cache
def lookalike_of(name: str) -> str | None:
    """The other format a pose in `name` is mistaken for in the reply's format warning: the other
    17-joint format (h36m17 and coco17 each other's), else None. The warning's geometry (nose_height,
    on COCO's torso) and threshold are that pair's; body25 and body25b, the other shared count, have
    no such test: their hints name both (suggest_formats)."""
    count = len(FORMATS[name].joint_names)
    if count != len(COCO17.joint_names):
        return None
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
    "openposecoco": "coco18",
    "openpose18": "coco18",
    "op18": "coco18",
    "openposebody25b": "body25b",
    "halpe": "halpe26",  # not "alphapose": its models are COCO 17, Halpe 26 or 136
    "coco": "coco17",
    "yolo": "coco17",
    "yolopose": "coco17",
    "yolov8": "coco17",
    "mmpose": "coco17",
    "detectron2": "coco17",
    "rtmpose": "coco17",
    "vitpose": "coco17",
    "cocowholebody": "wholebody133",
    "wholebody": "wholebody133",
    "rtmw": "wholebody133",
    "dwpose": "wholebody133",
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


def formats_with(count: int) -> tuple[str, ...]:
    """The formats whose poses have `count` joints, in FORMATS order."""
    return tuple(f.name for f in FORMATS.values() if len(f.joint_names) == count)


def suggest_formats(points: np.ndarray, present: np.ndarray) -> tuple[str, ...]:
    """The formats a pose of (K, 2) points (present (K,): the joints given) may be in: every format
    with K joints (one, or body25 and body25b, whose same joints sit in other places); for 17
    (h36m17 and coco17), the one joint 0's height above the shoulders points to (nose_height:
    above, COCO's nose; below, Human3.6M's pelvis), else none."""
    names = formats_with(len(points))
    if len(names) < 2 or len(points) != len(COCO17.joint_names):
        return names
    ok = present & np.isfinite(points).all(axis=-1)
    height = float(nose_height(np.asarray(points, np.float64)[None], ok[None])[0])
    if np.isnan(height):
        return ()
    return (COCO17.name if height > 0 else H36M17.name,)


def hint_for(points: np.ndarray, present: np.ndarray, given: str | None, flag: bool = False) -> str:
    """A hint for a pose that does not fit its format `given` (None: no format was sent): "; 25
    joints: this looks like body25 (OpenPose BODY_25) or body25b (...): send format \"body25\" or
    \"body25b\"" (`flag`: "use --format body25 or --format body25b", the command line's), or ""
    when nothing fits better."""
    found = [name for name in suggest_formats(points, present) if name != given]
    if not found:
        return ""
    described = " or ".join(f"{name} ({FORMATS[name].description})" for name in found)
    if flag:
        send = "use " + " or ".join(f"--format {name}" for name in found)
    else:
        send = "send format " + " or ".join(f'"{name}"' for name in found)
    return f"; {len(points)} joints: this looks like {described}: {send}"


def alternatives_note(name: str) -> str:
    """A note for poses read as `name` without --format: the other formats with as many joints,
    which the joints cannot tell from it ("25 joints read as body25 (OpenPose BODY_25); for OpenPose
    BODY_25B ... use --format body25b"), else "" (17 joints: the reply's format warning tells)."""
    count = len(FORMATS[name].joint_names)
    others = [other for other in formats_with(count) if other != name]
    if not others or count == len(COCO17.joint_names):
        return ""
    choices = "; ".join(f"for {FORMATS[o].description} use --format {o}" for o in others)
    return f"{count} joints read as {name} ({FORMATS[name].description}); {choices}"


def _openpose_formats(people: object) -> str:
    """The format(s) of an OpenPose frame's people, by the first one's joint count: "coco18" for 18,
    "body25" or "body25b" for 25 (and for a frame it cannot count)."""
    first = people[0] if isinstance(people, list) and people else None
    flat = first.get("pose_keypoints_2d") if isinstance(first, dict) else None
    count = len(flat) // 3 if isinstance(flat, list) else 0
    names = formats_with(count if count in OPENPOSE_FORMATS else len(BODY25.joint_names))
    return " or ".join(f'"{name}"' for name in names)


def raw_output_hint(data: object) -> str | None:
    """What to do with a detector's own output file posted as a POST /lift body, or None for any
    other body: an OpenPose --write_json frame ({"version", "people": [{"pose_keypoints_2d"}]}) or
    COCO keypoint results / annotations ([{"image_id", "keypoints": [x, y, s, ...]}]), or one of
    the files core.file_hints knows (MMPose, YOLO, MediaPipe, AlphaPose, COCO-WholeBody)."""
    if isinstance(data, dict) and "poses" in data:  # a POST /lift body: the usual case, at once
        return None
    if (hint := detector_file_hint(data)) is not None:
        return hint
    if isinstance(data, dict) and "people" in data:
        return (
            "this is OpenPose output (--write_json): use `repnet lift` on the file or folder, or send "
            'each person\'s pose_keypoints_2d as {"keypoints": [[x, y, c], ...]} with format '
            + _openpose_formats(data["people"])
        )
    items = data.get("annotations") if isinstance(data, dict) else data
    first = items[0] if isinstance(items, list) and items else None
    if isinstance(first, dict) and "keypoints" in first and ("image_id" in first or "category_id" in first):
        return (
            "this is COCO keypoint output ([{image_id, keypoints: [x, y, score, ...]}]): use `repnet lift` "
            'on the file, or send each result\'s keypoints as {"keypoints": [[x, y, score], ...]} with '
            'format "coco17"'
        )
    return None
