"""What a detector's own results file looks like when it is posted whole as a POST /lift body: MMPose
inferencer predictions, Ultralytics YOLO results, MediaPipe PoseLandmarker results, AlphaPose and
COCO-WholeBody keypoint lists (repnet.io.detectors reads each of them as a file)."""

from __future__ import annotations

from repnet.core.formats import FORMAT_BY_COUNT, WHOLEBODY_PARTS

_READ_IT = 'POST /lift takes {"poses": [...]}: read the file with `repnet lift FILE` or the page, or send'


def _first(data: object) -> object:
    """The first item of a list (of a list: a list of frames), else the value itself."""
    while isinstance(data, list) and data:
        data = data[0]
    return data


def _mmpose(item: dict[str, object]) -> str | None:
    if "frame_id" in item and "instances" in item:
        instances = item["instances"]
        item = (
            instances[0]
            if isinstance(instances, list) and instances and isinstance(instances[0], dict)
            else {}
        )
    keypoints = item.get("keypoints")
    if not isinstance(keypoints, list) or "keypoint_scores" not in item:
        return None
    fmt = FORMAT_BY_COUNT.get(len(keypoints), "coco17")
    return (
        f"this looks like an MMPose inferencer file (pred_out_dir); {_READ_IT} each instance's keypoints as "
        f'{{"keypoints": [[x, y], ...], "confidence": keypoint_scores}} with format "{fmt}"'
    )


def _yolo(item: dict[str, object]) -> str | None:
    if not isinstance(item.get("box"), dict) or not isinstance(item.get("keypoints"), dict):
        return None
    return (
        f"this looks like Ultralytics YOLO results (Results.summary() / to_json()); {_READ_IT} each "
        'detection\'s keypoints.x, keypoints.y as {"keypoints": [[x, y], ...], "confidence": '
        'keypoints.visible} with format "coco17"'
    )


def _mediapipe(item: dict[str, object]) -> str | None:
    if not any(key in item for key in ("pose_landmarks", "landmarks", "worldLandmarks")):
        return None
    return (
        f"this looks like a MediaPipe PoseLandmarker result; {_READ_IT} each pose's landmarks as "
        '{"keypoints": [[x, y, z, visibility], ...]} with format "mediapipe33" and image_size '
        "[width, height] in pixels"
    )


def _keypoint_list(item: dict[str, object]) -> str | None:
    """AlphaPose results ({image_id: "1.jpg", keypoints}) or COCO-WholeBody annotations."""
    keypoints = item.get("keypoints")
    if not isinstance(keypoints, list) or "image_id" not in item:
        return None
    if any(part in item for part in WHOLEBODY_PARTS[1:]):
        return (
            f"this looks like a COCO-WholeBody annotation file; {_READ_IT} each annotation's keypoints, "
            'foot_kpts, face_kpts, lefthand_kpts and righthand_kpts joined as {"keypoints": [[x, y, v], '
            '...]} with format "wholebody133"'
        )
    fmt = FORMAT_BY_COUNT.get(len(keypoints) // 3)
    if fmt == "coco17" and not isinstance(item["image_id"], str):
        return None  # COCO results: format_hints.raw_output_hint names them
    return (
        f"this looks like AlphaPose results (alphapose-results.json); {_READ_IT} each result's keypoints "
        f'as {{"keypoints": [[x, y, score], ...]}} with format "{fmt or "coco17"}"'
    )


def detector_file_hint(data: object) -> str | None:
    """What to do with one of these files posted as a body, or None for any other body (a POST /lift
    body, with "poses", is not one: format_hints.raw_output_hint looks no further)."""
    annotations = isinstance(data, dict) and isinstance(data.get("annotations"), list)
    items = data["annotations"] if isinstance(data, dict) and annotations else data
    first = _first(items)
    if not isinstance(first, dict):
        return None
    for hint in (_mmpose, _yolo, _mediapipe, _keypoint_list):
        if (found := hint(first)) is not None:
            return found
    return None
