"""Pose files for the `repnet` command: JSON, NPZ and folders (or globs) of OpenPose frames."""

from __future__ import annotations

import glob
import zipfile
from collections.abc import Callable, Iterable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from repnet.core.contract import MAX_FRAME, is_frame_number
from repnet.io.coco import boxes_only, is_coco, read_coco
from repnet.io.detectors import (
    is_mediapipe_result,
    is_mmpose,
    is_yolo_summary,
    read_mediapipe_result,
    read_mmpose,
    read_yolo_summary,
    read_yolo_txt,
)
from repnet.io.poses import (
    InputFileError,
    Poses,
    frame_number,
    openpose_format,
    openpose_people,
    pose_array,
    read_json,
    shown,
    stack_poses,
)

Progress = Callable[[Sequence[Path]], Iterable[Path]]


def _fps(data: Any) -> float | None:
    """The frame rate a file gives (`fps`), if it does."""
    fps = data.get("fps") if isinstance(data, dict) else None
    if fps is None:
        return None
    if not isinstance(fps, int | float) or isinstance(fps, bool) or not 0 < fps < float("inf"):
        raise InputFileError(f"fps: expected a number > 0, got {shown(fps)}")
    return float(fps)


def _openpose_frames(frames: Sequence[Any]) -> Poses:
    """OpenPose frames in one list, each frame's people numbered by the frame's index."""
    people = [(f, k, p) for f, frame in enumerate(frames) for k, p in enumerate(openpose_people(frame))]
    poses = stack_poses([p for _, _, p in people], None, openpose_format([p for _, _, p in people]), "frames")
    return replace(
        poses, frame=np.array([f for f, _, _ in people]), person=np.array([k for _, k, _ in people])
    )


def _lift_body(data: dict[str, Any]) -> Poses:
    """A POST /lift body, with the tracks and frame numbers its poses give."""
    items = data["poses"] if isinstance(data["poses"], list) else []
    arrays = [
        pose_array(p.get("keypoints") if isinstance(p, dict) else None, f"poses[{i}].keypoints")
        for i, p in enumerate(items)
    ]
    for pose, item in zip(arrays, items, strict=True):
        if isinstance(item, dict) and item.get("confidence") is not None:
            pose[:, 2] = np.asarray(item["confidence"], dtype=np.float64)
    poses = replace(stack_poses(arrays, None, data.get("format"), "poses"), fps=_fps(data))
    sizes = [
        _size(p.get("image_size") or data.get("image_size"), f"poses[{i}].image_size")
        for i, p in enumerate(items)
    ]
    if any(s is not None for s in sizes):
        poses = replace(poses, image_size=np.array([(np.nan, np.nan) if s is None else s for s in sizes]))
    tracks = [str(p["track_id"]) if p.get("track_id") is not None else None for p in items]
    if not any(t is not None for t in tracks):
        return poses
    frames = [p.get("frame") for p in items]
    for i, (f, t) in enumerate(zip(frames, tracks, strict=True)):
        if t is not None and not is_frame_number(f):
            raise InputFileError(
                f"poses[{i}].frame: a pose with a track_id needs its frame number, an integer from 0 to "
                f"{MAX_FRAME}, got {shown(f)}"
            )
    numbers = np.array([f if is_frame_number(f) else i for i, f in enumerate(frames)], np.int64)
    return replace(poses, frame=numbers, track_id=tuple(tracks))


def _size(value: Any, where: str) -> tuple[float, float] | None:
    """An image_size [width, height] px, or None."""
    if value is None:
        return None
    ok = isinstance(value, list) and len(value) == 2 and all(isinstance(v, int | float) for v in value)
    if not ok or not all(0 < v < float("inf") for v in value):
        raise InputFileError(f"{where}: expected [width, height] in pixels (> 0), got {shown(value)}")
    return (float(value[0]), float(value[1]))


def to_pixels(poses: Poses, image_size: tuple[float, float] | None) -> Poses:
    """The poses with normalised x, y multiplied by their image size: the file's (a POST /lift body's
    image_size), else `image_size` (--image-size) for every pose; InputFileError for MediaPipe rows
    with neither."""
    n = len(poses.points)
    size = np.full((n, 2), np.nan) if poses.image_size is None else poses.image_size
    if image_size is not None:
        size = np.where(np.isnan(size), np.asarray(image_size, np.float64), size)
    unscaled = np.isnan(size).any(axis=1)  # (N,)
    normalised = np.full(n, poses.normalised is not None) if poses.landmarks is None else poses.landmarks
    if (normalised & unscaled).any():
        first = int(np.flatnonzero(normalised & unscaled)[0])
        what = poses.normalised or "rows of 4 values are MediaPipe landmarks [x, y, z, visibility]"
        raise InputFileError(
            f"poses[{first}]: {what} with x, y normalised to [0, 1]: give the image size with "
            "--image-size W H (or image_size in the file)"
        )
    points = np.where(unscaled[:, None, None], poses.points, poses.points * size[:, None, :])
    return replace(poses, points=points, image_size=None, landmarks=None, normalised=None)


def _read_json(data: Any) -> Poses:
    if isinstance(data, dict) and "people" in data:  # one OpenPose frame: every person a pose
        people = openpose_people(data)
        poses = stack_poses(people, None, openpose_format(people), "people")
        return replace(poses, frame=np.zeros(len(people), int), person=np.arange(len(people)))
    if isinstance(data, list) and data and all(isinstance(f, dict) and "people" in f for f in data):
        return _openpose_frames(data)
    if is_mmpose(data):
        return read_mmpose(data)
    if is_yolo_summary(data):
        return read_yolo_summary(data)
    if is_mediapipe_result(data):
        return read_mediapipe_result(data)
    if is_coco(data):  # detector results
        return read_coco(data, "results")
    if boxes_only(data):
        raise InputFileError(
            "COCO detections with boxes and no keypoints: this is a person detector's output; lift the "
            "output of a pose (keypoint) detector instead"
        )
    if isinstance(data, dict) and isinstance(data.get("annotations"), list):
        return read_coco(data["annotations"], "annotations")
    if isinstance(data, dict) and "poses" in data:  # the POST /lift body
        return _lift_body(data)
    body = data if isinstance(data, dict) else {"keypoints": data}
    keypoints, fmt = body.get("keypoints"), body.get("format")
    many = (
        isinstance(keypoints, list)
        and bool(keypoints)
        and isinstance(keypoints[0], list)
        and any(isinstance(row, list) for row in keypoints[0])
    )
    rows: list[Any] = keypoints if many and isinstance(keypoints, list) else [keypoints]
    poses = stack_poses(
        [pose_array(r, f"keypoints[{i}]") for i, r in enumerate(rows)],
        body.get("confidence"),
        fmt,
        "keypoints",
    )
    return replace(poses, fps=_fps(body))


# What one input file may hold, so that a small file cannot take the machine's memory: an NPZ's
# arrays once inflated (zip's deflate packs 1000:1, so the file's own size says little), and a JSON
# file's text (Python's parser holds about 20x the text: 64 MiB of JSON peaks near 1.3 GB).
MAX_NPZ_ARRAY_BYTES = 512 * 1024 * 1024
MAX_JSON_BYTES = 64 * 1024 * 1024


def check_input_size(path: Path) -> None:
    """InputFileError naming `path` when it holds more than this reader takes (MAX_NPZ_ARRAY_BYTES,
    MAX_JSON_BYTES), read from the zip directory or the file size before anything is loaded."""
    if path.suffix == ".npz":
        try:
            with zipfile.ZipFile(path) as archive:  # zipfile reads an entry up to its declared size only
                inflated = sum(entry.file_size for entry in archive.infolist())
        except zipfile.BadZipFile as err:
            raise InputFileError(f"{path}: not an NPZ file ({err})") from None
        if inflated > MAX_NPZ_ARRAY_BYTES:
            raise InputFileError(
                f"{path}: its arrays hold {inflated} bytes once inflated, more than {MAX_NPZ_ARRAY_BYTES}; "
                "split the input into several files"
            )
    elif path.suffix in (".json", ".txt") and (size := path.stat().st_size) > MAX_JSON_BYTES:
        raise InputFileError(
            f"{path}: {size} bytes of {path.suffix[1:].upper()}, more than {MAX_JSON_BYTES}; write it as "
            "an .npz (binary, 10x smaller) or split it into several files"
        )


def _load_npz(path: Path) -> Poses:
    """Poses of an NPZ: `keypoints` (N, J, 2|3|4) or (J, 2|3|4), optional confidence, format, fps."""
    with np.load(path, allow_pickle=False) as npz:
        if "keypoints" not in npz:
            raise InputFileError(f"{path}: no 'keypoints' array (has {', '.join(npz.files)})")
        raw = npz["keypoints"]
        if raw.dtype.kind not in "iuf":  # complex, bool, text, ...: no coordinates
            raise InputFileError(f"{path}: 'keypoints' must hold real numbers, got dtype {raw.dtype}")
        keypoints = np.asarray(raw, dtype=np.float64)
        conf = npz["confidence"] if "confidence" in npz else None
        fmt = npz["format"] if "format" in npz else None
        fps = float(npz["fps"]) if "fps" in npz else None
        frame = npz["frame"] if "frame" in npz else None
    keypoints = keypoints[None] if keypoints.ndim == 2 else keypoints
    if keypoints.ndim != 3 or keypoints.shape[-1] not in (2, 3, 4):
        raise InputFileError(f"expected keypoints (N, J, 2|3|4), got {keypoints.shape}")
    landmarks = np.full(len(keypoints), keypoints.shape[-1] == 4)  # MediaPipe [x, y, z, visibility]
    keypoints = keypoints[..., [0, 1, 3]] if keypoints.shape[-1] == 4 else keypoints
    padded = np.pad(keypoints, ((0, 0), (0, 0), (0, 3 - keypoints.shape[-1])), constant_values=np.nan)
    poses = stack_poses(list(padded), conf, fmt, str(path))
    numbers = poses.frame if frame is None else _npz_frames(frame, len(keypoints), path)
    return replace(
        poses, fps=_fps({"fps": fps}), landmarks=landmarks if landmarks.any() else None, frame=numbers
    )


def _npz_frames(frame: np.ndarray, count: int, path: Path) -> np.ndarray:
    """An NPZ's optional `frame` array: each pose's frame number (N,), integers 0..MAX_FRAME, so that
    a clip with gaps (frames a detector missed) is read as one."""
    if frame.dtype.kind not in "iu" or frame.shape != (count,):
        raise InputFileError(
            f"{path}: 'frame' must be ({count},) integers, one frame number per pose; "
            f"got {frame.dtype} {frame.shape}"
        )
    if count and (frame.min() < 0 or frame.max() > MAX_FRAME):
        got = f"{frame.min()}..{frame.max()}"
        raise InputFileError(f"{path}: 'frame' numbers must be 0..{MAX_FRAME}, got {got}")
    return frame.astype(np.int64)


def load_poses(path: Path) -> Poses:
    """Poses from a .json (a pose, a list of poses, a POST /lift body, OpenPose, COCO, AlphaPose,
    MMPose, YOLO or MediaPipe results: repnet.io.detectors), a YOLO label .txt or an .npz
    (`keypoints` (N, J, 2|3|4) or (J, 2|3|4) with NaN for missing joints, optional `confidence`,
    `format`; 4 values are MediaPipe's [x, y, z, visibility], to scale by an image size)."""
    try:
        check_input_size(path)
        if path.suffix == ".npz":
            return _load_npz(path)
        if path.suffix == ".txt":  # a YOLO-pose label file (save_txt)
            return read_yolo_txt(path.read_text(), path.name)
        if path.suffix == ".json":
            data = read_json(path)
            poses = _read_json(data)
            if isinstance(data, dict) and "people" in data and (number := frame_number(path)) is not None:
                poses = replace(poses, frame=np.full(len(poses.frame), number))  # one OpenPose frame
            return poses
    except InputFileError as err:  # named by the file it is about (one of a folder's, say)
        if str(path) in str(err):
            raise
        raise InputFileError(f"{path}: {err}") from None
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as err:
        raise InputFileError(f"{path}: {err}") from err
    raise InputFileError(f"{path}: expected a .json, .npz or .txt (YOLO labels) file")


def _load_in_pixels(path: Path, image_size: tuple[float, float] | None) -> Poses:
    """load_poses(path) in pixels (to_pixels), every error named by the file."""
    poses = load_poses(path)  # its errors name the file
    try:
        return to_pixels(poses, image_size)
    except InputFileError as err:
        raise InputFileError(f"{path}: {err}") from None


def _frame_files(spec: str) -> list[Path]:
    """The .json files of a folder, or the files a glob pattern matches, by frame number then name."""
    path = Path(spec)
    if path.is_dir():
        files = sorted(path.glob("*.json")) or sorted(path.glob("*.txt"))  # OpenPose's, else YOLO labels
        where = f"{path}: no .json or .txt files in the folder"
    else:
        files = [Path(p) for p in glob.glob(spec)]
        where = f"{spec}: no file matches"
    if not files:
        raise InputFileError(where)
    return sorted(files, key=lambda f: (frame_number(f) is None, frame_number(f) or 0, f.name))


def _blank(path: Path) -> bool:
    """A text file with nothing but white space in it."""
    try:
        return not path.read_text().strip()
    except (OSError, ValueError) as err:
        raise InputFileError(f"{path}: {err}") from err


def load_frames(
    files: Sequence[Path], progress: Progress, image_size: tuple[float, float] | None = None
) -> Poses:
    """Every person of every frame file (OpenPose per-frame JSON, or any pose file), in frame order;
    a frame without people gives no pose."""
    parts: list[np.ndarray] = []
    frames: list[int] = []
    persons: list[int] = []
    labels: list[str] = []  # the file each pose came from
    fmt: str | None = None
    for index, path in enumerate(progress(files)):
        data = read_json(path) if path.suffix == ".json" else None
        number = frame_number(path)
        rows: list[np.ndarray] = []
        names: list[str] = []  # each row's label, when not its file's name
        if path.suffix == ".txt" and _blank(path):  # a frame's label file without a person
            pass
        elif isinstance(data, dict) and "people" in data:
            try:
                people = openpose_people(data)
            except (KeyError, ValueError, TypeError) as err:
                raise InputFileError(f"{path}: {err}") from err
            fmt = fmt or openpose_format(people)
            scale = np.array([*(image_size or (1.0, 1.0)), 1.0])  # --keypoint_scale 3 writes [0, 1]
            rows = [p * scale for p in people]
        else:
            poses = _load_in_pixels(path, image_size)
            fmt = fmt or poses.format
            conf = np.full(poses.points.shape[:2], np.nan) if poses.confidence is None else poses.confidence
            rows = list(np.concatenate([poses.points, conf[..., None]], axis=-1))
            if data is None and poses.label:  # a label file's own labels (its line numbers)
                names = list(poses.label)
        parts += rows
        frames += [index if number is None else number] * len(rows)
        persons += range(len(rows))
        labels += names or [path.name] * len(rows)
    poses = stack_poses(parts, None, fmt, f"{len(files)} files")
    return replace(
        poses, frame=np.array(frames), person=np.array(persons), label=tuple(labels), numbered_by="file names"
    )


def read_input(spec: str, progress: Progress, image_size: tuple[float, float] | None = None) -> Poses:
    """Poses from one file, or from every frame file of a folder or a glob pattern, in pixels
    (normalised coordinates multiplied by their image size: the file's, else `image_size`)."""
    path = Path(spec)
    if path.is_file():
        return _load_in_pixels(path, image_size)
    if path.is_dir() or any(c in spec for c in "*?["):
        return load_frames(_frame_files(spec), progress, image_size)
    raise InputFileError(f"{spec}: No such file or folder")
