"""COCO-style keypoint lists: COCO results and annotations, AlphaPose results (Halpe-26, COCO-17 or
133 joints) and COCO-WholeBody annotations, their format by joint count and frames by image id."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from repnet.core.contract import is_frame_number
from repnet.core.formats import FORMAT_BY_COUNT
from repnet.io.detectors import wholebody_triples
from repnet.io.poses import InputFileError, Poses, frame_number, shown, stack_poses


def image_frames(ids: Sequence[Any]) -> tuple[np.ndarray, str]:
    """Frame numbers of COCO image ids: an integer id is its frame, a text id (AlphaPose's file name
    "12.jpg") the last number in it; else the ids in order of appearance; and what they are
    (Poses.numbered_by)."""
    numbers = [
        i if isinstance(i, int) else (frame_number(Path(i)) if isinstance(i, str) else None) for i in ids
    ]
    if all(is_frame_number(n) for n in numbers):
        return np.array(numbers, dtype=np.int64), "image ids"
    return np.unique([str(i) for i in ids], return_inverse=True)[1].astype(np.int64), "image names"


def read_coco(items: Sequence[Any], where: str) -> Poses:
    """COCO keypoint results ([{image_id, keypoints: [x, y, score, ...]}]), AlphaPose results or
    annotations (a third value 0, 1 or 2 flags a joint; 0 is missing; COCO-WholeBody's parts joined),
    ordered by image; a joint with 0 is missing. The format by joint count: 17 coco17, 26 halpe26,
    133 wholebody133."""
    found = [a for a in items if isinstance(a, dict) and isinstance(a.get("keypoints"), list)]
    if not found:
        boxes = (
            " (boxes only: a person detector's output, not a pose detector's)" if boxes_only(items) else ""
        )
        raise InputFileError(f"{where}: no keypoints{boxes}")
    rows = [np.asarray(wholebody_triples(a), dtype=np.float64).reshape(-1, 3) for a in found]
    flags = all(np.isin(r[:, 2], (0, 1, 2)).all() for r in rows)
    poses = []
    for r in rows:
        pose = np.where(r[:, 2:] > 0, r, np.nan)  # (K, 3) a joint with 0 is missing
        if flags:  # flags are no confidence
            pose[:, 2] = np.nan
        poses.append(pose)
    frames, by_ids = image_frames([a.get("image_id", k) for k, a in enumerate(found)])
    numbered_by = by_ids if any("image_id" in a for a in found) else None  # else the poses' order in the file
    order = np.argsort(frames, kind="stable")
    fmt = FORMAT_BY_COUNT.get(len(rows[0]))
    stacked = stack_poses([poses[k] for k in order], None, fmt, where)
    person = np.zeros(len(order), np.int64)
    for k in range(1, len(order)):
        person[k] = person[k - 1] + 1 if frames[order[k]] == frames[order[k - 1]] else 0
    labels = tuple(coco_label(found[k]) for k in order)
    return replace(stacked, frame=frames[order], person=person, label=labels, numbered_by=numbered_by)


def coco_label(item: dict[str, Any]) -> str:
    """A COCO detection or annotation as the file names it: its image id, and its own id (AlphaPose's
    idx) if any."""
    named = [
        f"{key} {shown(item[key]) if isinstance(item[key], str) else item[key]}"
        for key in ("image_id", "id", "idx")
        if key in item and isinstance(item[key], int | str)
    ]
    return ", ".join(named) or "no id"


def boxes_only(data: Any) -> bool:
    """COCO detections or annotations that have boxes and no keypoints."""
    return (
        isinstance(data, list)
        and bool(data)
        and all(isinstance(a, dict) and "bbox" in a and "keypoints" not in a for a in data)
    )


def is_coco(data: Any) -> bool:
    """A list of objects with flat keypoints [x, y, v, ...]: COCO results or AlphaPose's."""
    return (
        isinstance(data, list)
        and bool(data)
        and all(
            isinstance(a, dict)
            and isinstance(a.get("keypoints"), list)
            and all(isinstance(v, int | float) for v in a["keypoints"])
            for a in data
        )
    )
