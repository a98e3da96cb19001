"""Detector files read as their tools write them: MMPose inferencer predictions, Ultralytics YOLO-pose
summaries and label files, MediaPipe PoseLandmarker results, and the joint count of a COCO-style list
(COCO-17, Halpe-26 / AlphaPose, COCO-WholeBody 133). static/detectors.js reads the same layouts."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from repnet.core.formats import FORMAT_BY_COUNT, WHOLEBODY_PARTS
from repnet.io.poses import InputFileError, Poses, shown, stack_poses

YOLO_JOINTS = 17  # Ultralytics' pose models: the COCO-17 keypoints (kpt_shape [17, 3] or [17, 2])


def _is_number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)


def _numbers(values: Any, where: str) -> list[float]:
    if not isinstance(values, list) or not all(_is_number(v) for v in values):
        raise InputFileError(f"{where}: expected a list of numbers, got {shown(values)}")
    return [float(v) for v in values]


def _located(poses: Poses, frames: Sequence[int], people: Sequence[int], labels: Sequence[str]) -> Poses:
    return replace(
        poses, frame=np.array(frames, np.int64), person=np.array(people, np.int64), label=tuple(labels)
    )


def wholebody_triples(item: dict[str, Any]) -> Any:
    """A COCO-WholeBody annotation's flat x, y, v values in the 133 joints' order (its parts joined),
    or the item's `keypoints` as they are when it has no other part."""
    if not any(part in item for part in WHOLEBODY_PARTS[1:]):
        return item.get("keypoints")
    flat: list[Any] = []
    for part in WHOLEBODY_PARTS:
        values = item.get(part)
        if not isinstance(values, list):
            raise InputFileError(
                f"{part}: a COCO-WholeBody annotation has all of {', '.join(WHOLEBODY_PARTS)}"
            )
        flat += values
    return flat


# ---- MMPose: MMPoseInferencer(..., pred_out_dir=...) ----


def _is_instance(item: Any) -> bool:
    return isinstance(item, dict) and isinstance(item.get("keypoints"), list) and "keypoint_scores" in item


def is_mmpose(data: Any) -> bool:
    """A video's predictions [{frame_id, instances: [...]}] or an image's instances [{keypoints: [[x, y],
    ...], keypoint_scores, bbox?}]."""
    if not isinstance(data, list) or not data:
        return False
    video = all(isinstance(f, dict) and "frame_id" in f and "instances" in f for f in data)
    return video or all(_is_instance(i) for i in data)


def _mmpose_pose(item: Any, where: str) -> np.ndarray:
    if not _is_instance(item):
        raise InputFileError(f"{where}: expected an instance {{keypoints: [[x, y], ...], keypoint_scores}}")
    rows = item["keypoints"]
    if not all(isinstance(r, list) and len(r) == 2 and all(_is_number(v) for v in r) for r in rows):
        raise InputFileError(
            f"{where}.keypoints: expected [x, y] rows (MMPose's 2D keypoints), got {shown(rows)}"
        )
    scores = _numbers(item["keypoint_scores"], f"{where}.keypoint_scores")
    if len(scores) != len(rows):
        raise InputFileError(f"{where}.keypoint_scores: expected {len(rows)} scores, got {len(scores)}")
    # RTMPose's scores are SimCC maxima, not probabilities, and pass 1 (mmpose issues 2755, 3122): above
    # 1 is read as sure, so that a confidence threshold keeps its meaning and the range rule holds.
    sure = np.minimum(np.asarray(scores), 1.0)
    return np.concatenate([np.asarray(rows, np.float64).reshape(-1, 2), sure[:, None]], axis=1)


def read_mmpose(data: list[Any]) -> Poses:
    """MMPose inferencer predictions: frames from frame_id (an image's file: frame 0), people by
    instance index; the format by joint count (17 coco17, 26 halpe26, 133 wholebody133)."""
    video = all(isinstance(f, dict) and "frame_id" in f for f in data)
    frames: list[Any] = data if video else [{"frame_id": 0, "instances": data}]
    poses, at, people, labels = [], [], [], []
    for f, frame in enumerate(frames):
        number, items = frame["frame_id"], frame["instances"]
        if not isinstance(number, int) or isinstance(number, bool) or number < 0:
            raise InputFileError(f"[{f}].frame_id: expected a frame number >= 0, got {shown(number)}")
        if not isinstance(items, list):
            raise InputFileError(f"[{f}].instances: expected a list, got {shown(items)}")
        for k, item in enumerate(items):
            poses.append(_mmpose_pose(item, f"[{f}].instances[{k}]" if video else f"[{k}]"))
            at.append(number)
            people.append(k)
            labels.append(f"frame_id {number}, instance {k}" if video else f"instance {k}")
    if not poses:
        raise InputFileError("MMPose predictions: no instances in any frame")
    stacked = stack_poses(poses, None, FORMAT_BY_COUNT.get(len(poses[0])), "MMPose instances")
    return _located(stacked, at, people, labels)


# ---- Ultralytics YOLO-pose: Results.summary() / to_json(), and save_txt label files ----


def _is_yolo_item(item: Any) -> bool:
    return (
        isinstance(item, dict)
        and isinstance(item.get("box"), dict)
        and isinstance(item.get("keypoints"), dict)
    )


def is_yolo_summary(data: Any) -> bool:
    """One image's [{name, class, confidence, box, keypoints: {x, y, visible}}], or a list of them."""
    if not isinstance(data, list) or not data:
        return False
    if all(isinstance(f, list) for f in data):
        return any(f for f in data) and all(_is_yolo_item(i) for f in data for i in f)
    return all(_is_yolo_item(i) for i in data)


def read_yolo_summary(data: list[Any]) -> Poses:
    """YOLO-pose detections (a list of frames when the file holds lists): keypoints x, y and their
    visible score; coordinates all within [0, 1] are summary(normalize=True)'s, to scale by the
    image size."""
    frames = data if all(isinstance(f, list) for f in data) else [data]
    poses, at, people, labels, coords = [], [], [], [], []
    nested = frames is data
    for f, items in enumerate(frames):
        for k, item in enumerate(items):
            where = f"[{f}][{k}]" if nested else f"[{k}]"
            points = item["keypoints"]
            x, y = (
                _numbers(points.get("x"), f"{where}.keypoints.x"),
                _numbers(points.get("y"), f"{where}.keypoints.y"),
            )
            seen = points.get("visible")
            c = [np.nan] * len(x) if seen is None else _numbers(seen, f"{where}.keypoints.visible")
            if not len(x) == len(y) == len(c) or not x:
                raise InputFileError(
                    f"{where}.keypoints: x, y and visible must be equally long, non-empty lists"
                )
            box = [item["box"].get(key) for key in ("x1", "y1", "x2", "y2")]
            coords += [*x, *y, *_numbers(box, f"{where}.box")]
            poses.append(np.stack([x, y, c], axis=1))
            at.append(f)
            people.append(k)
            labels.append(f"image {f}, detection {k}" if nested else f"detection {k}")
    if not poses:
        raise InputFileError("YOLO results: no detections")
    stacked = _located(
        stack_poses(poses, None, FORMAT_BY_COUNT.get(len(poses[0])), "YOLO detections"), at, people, labels
    )
    unit = all(0.0 <= v <= 1.0 for v in coords)
    return replace(stacked, normalised="YOLO results (summary(normalize=True))") if unit else stacked


def read_yolo_txt(text: str, name: str) -> Poses:
    """A YOLO-pose label file (save_txt): one line per person, `class cx cy w h` then 17 keypoints of
    x y [visibility] normalised to [0, 1], then the box confidence (save_conf) and track id if saved."""
    poses, labels = [], []
    for n, line in enumerate(text.splitlines(), start=1):
        if not line.strip():
            continue
        try:
            values = [float(v) for v in line.split()]
            if not np.isfinite(values).all():
                raise ValueError
        except ValueError:
            raise InputFileError(f"line {n}: expected finite numbers, got {shown(line)}") from None
        extra = len(values) - 5 - 3 * YOLO_JOINTS  # with visibility: 0, 1 or 2 values after the joints
        width = 3 if 0 <= extra <= 2 else 2
        extra = extra if width == 3 else len(values) - 5 - 2 * YOLO_JOINTS
        if not 0 <= extra <= 2:
            raise InputFileError(
                f"line {n}: expected class cx cy w h and {YOLO_JOINTS} keypoints of x y [visibility] "
                f"({5 + 2 * YOLO_JOINTS} to {7 + 3 * YOLO_JOINTS} numbers), got {len(values)} values"
            )
        joints = np.asarray(values[5 : 5 + width * YOLO_JOINTS]).reshape(YOLO_JOINTS, width)
        poses.append(joints if width == 3 else np.pad(joints, ((0, 0), (0, 1)), constant_values=np.nan))
        labels.append(f"{name} line {n}")
    stacked = stack_poses(poses, None, "coco17", name)
    located = _located(stacked, [0] * len(poses), range(len(poses)), labels)
    return replace(located, normalised="YOLO label rows")


# ---- MediaPipe PoseLandmarker (Tasks API) results ----


def _result_landmarks(data: Any) -> Any:
    """The poses of one PoseLandmarkerResult: Python's pose_landmarks or the JS API's landmarks."""
    if not isinstance(data, dict):
        return None
    poses = data.get("pose_landmarks", data.get("landmarks"))
    ok = isinstance(poses, list) and all(
        isinstance(p, list) and all(isinstance(m, dict) and "x" in m and "y" in m for m in p) for p in poses
    )
    return poses if ok else None


def is_mediapipe_result(data: Any) -> bool:
    """A PoseLandmarkerResult as JSON ({pose_landmarks | landmarks: [[{x, y, z, visibility}, ...]]}), or
    a list of them, one per frame."""
    results = data if isinstance(data, list) and data else [data]
    return all(_result_landmarks(r) is not None for r in results)


def read_mediapipe_result(data: Any) -> Poses:
    """Landmarks [x, y] normalised to [0, 1] of the image, their visibility the confidence; frames by
    the result's index; world landmarks are not read."""
    results = data if isinstance(data, list) else [data]
    poses, at, people, labels = [], [], [], []
    for f, result in enumerate(results):
        for k, marks in enumerate(_result_landmarks(result)):
            rows = np.full((len(marks), 4), np.nan)
            given = any(m.get("visibility") is not None for m in marks)  # else no confidence at all
            for j, mark in enumerate(marks):
                seen = mark.get("visibility")
                values = [mark["x"], mark["y"], 0.0 if seen is None else seen]
                if not all(_is_number(v) for v in values):
                    raise InputFileError(
                        f"[{f}] pose {k} landmark {j}: expected numbers x, y, visibility, got {shown(mark)}"
                    )
                rows[j] = [mark["x"], mark["y"], values[2] if given else np.nan, 1.0]
            poses.append(rows)
            at.append(f)
            people.append(k)
            labels.append(f"result {f}, pose {k}")
    if not poses:
        raise InputFileError("MediaPipe results: no pose in any result")
    stacked = _located(stack_poses(poses, None, "mediapipe33", "landmarks"), at, people, labels)
    return replace(stacked, normalised="MediaPipe PoseLandmarker landmarks")
