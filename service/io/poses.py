"""Poses read from a file, the errors of reading one, and the pieces every file layout is read with: a
pose's rows, a stack of poses, an OpenPose frame's people, a frame number in a file name, a JSON file
read safely."""

from __future__ import annotations

import json
import re
from collections.abc import Hashable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from repnet.core.contract import MAX_FRAME
from repnet.core.errors import MAX_ECHO_CHARS
from repnet.core.formats import OPENPOSE_FORMATS
from repnet.core.links import Links, previous_frames


class InputFileError(Exception):
    """The input file cannot be read as poses."""


@dataclass(frozen=True)
class Poses:
    """Poses read from a file or a folder of frames, in frame order."""

    points: np.ndarray  # (N, J, 2) px, NaN where a joint is missing
    confidence: np.ndarray | None  # (N, J) in [0, 1], or None
    format: str | None  # the format the file names, if any
    frame: np.ndarray  # (N,) int: the frame of each pose (file number, else its index in the file)
    person: np.ndarray  # (N,) int: the pose's index among the people of its frame
    fps: float | None = None  # the frame rate the file gives (`fps`), if it does
    track_id: tuple[str | None, ...] | None = None  # the tracks the file gives (a POST /lift body's)
    # (N, 2) the image size [width, height] px a pose's x, y are normalised by (a POST /lift body's
    # image_size), NaN where the file gives none; None: none given
    image_size: np.ndarray | None = None
    landmarks: np.ndarray | None = None  # (N,) the pose's rows were MediaPipe [x, y, z, visibility]
    # (N,) what the file calls each pose, where it names them (a COCO file: "image_id 397133, id 1768")
    label: tuple[str, ...] | None = None
    # what the frame numbers are when they may be unrelated images' rather than a clip's: "image ids"
    # (COCO), "file names" (a folder's), "image names" (ids with no number: frames in order of first
    # appearance); None: the poses' order in the file, or its frame fields (a clip)
    numbered_by: str | None = None
    # the layout whose x, y are normalised to [0, 1] of the image, to scale by its size (YOLO labels)
    normalised: str | None = None

    @property
    def frame_count(self) -> int:
        """How many frames the poses are of: more than one makes a sequence."""
        return len(np.unique(self.frame))

    def previous_frames(self) -> Links:
        """(N,) per pose the row of the same person's pose in the frame before it, -1 where there
        is none (core.links). A person is known across frames by the tracks the file gives, or as
        the one person of a clip whose every frame holds one pose; frames numbered by image ids or
        file names are unrelated images and link nothing."""
        n = len(self.points)
        people: list[Hashable | None] = [None] * n
        if self.numbered_by is None:
            if self.track_id is not None and any(t is not None for t in self.track_id):
                people = list(self.track_id)
            elif self.frame_count == n:
                people = [0] * n
        return previous_frames(self.frame, people)


ROW_HINT = (
    "each joint is [x, y] or [x, y, confidence] in pixels, MediaPipe's [x, y, z, visibility] (with "
    "--image-size W H, or image_size in a POST /lift body), or null; `repnet lift --help` lists the "
    "files it reads (OpenPose, COCO, MMPose, YOLO, MediaPipe, AlphaPose, POST /lift bodies, NPZ)"
)


def shown(value: Any) -> str:
    """A value of the input quoted in an error, cut to MAX_ECHO_CHARS characters with its length."""
    text = repr(value)
    return text if len(text) <= MAX_ECHO_CHARS else f"{text[:MAX_ECHO_CHARS]}… ({len(text)} characters)"


def pose_array(rows: Any, where: str) -> np.ndarray:
    """One pose of J rows ([x, y], [x, y, c], [x, y, z, visibility] or null) -> (J, 4): x, y, c (the
    visibility of a MediaPipe row; NaN if not given), and 1 where the row was MediaPipe's; NaN rows
    for null."""
    if not isinstance(rows, list) or not rows:
        raise InputFileError(f"{where}: expected a non-empty list of joints, got {shown(rows)}; {ROW_HINT}")
    out = np.full((len(rows), 4), np.nan)
    for j, row in enumerate(rows):
        if row is None:
            continue
        numbers = isinstance(row, list) and all(isinstance(v, int | float) for v in row)
        if not numbers or len(row) not in (2, 3, 4):
            raise InputFileError(f"{where}[{j}]: expected a joint, got {shown(row)}; {ROW_HINT}")
        out[j, : min(len(row), 3)] = row[:2] + row[-1:] if len(row) == 4 else row
        out[j, 3] = 1.0 if len(row) == 4 else np.nan
    return out


def stack_poses(poses: Sequence[np.ndarray], confidence: Any, fmt: Any, where: str) -> Poses:
    """(J, 3) poses from pose_array, with `confidence` (N, J) overriding their third column; one
    frame per pose."""
    if not poses:
        raise InputFileError(f"{where}: no poses")
    if len({p.shape for p in poses}) != 1:
        raise InputFileError(f"{where}: poses have different joint counts {sorted({len(p) for p in poses})}")
    data = np.stack(poses)  # (N, J, 3 or 4)
    if confidence is None and not np.isnan(data[..., 2]).all():
        confidence = np.nan_to_num(data[..., 2], nan=1.0)  # a joint given without confidence counts as sure
    conf = None if confidence is None else np.asarray(confidence, dtype=np.float64).reshape(data.shape[:2])
    n = len(poses)
    landmarks = (data[..., 3] == 1).any(axis=1) if data.shape[-1] > 3 else np.zeros(n, bool)
    return Poses(
        data[..., :2],
        conf,
        None if fmt is None else str(fmt),
        np.arange(n),
        np.zeros(n, int),
        landmarks=landmarks if landmarks.any() else None,
    )


def openpose_people(data: dict[str, Any]) -> list[np.ndarray]:
    """OpenPose --write_json people as (J, 3) x, y, c arrays; c = 0 marks a missing joint (NaN)."""
    people = [np.asarray(p["pose_keypoints_2d"], dtype=np.float64).reshape(-1, 3) for p in data["people"]]
    return [np.where(p[:, 2:] > 0, p, np.nan) for p in people]


def openpose_format(people: Sequence[np.ndarray]) -> str | None:
    """The format of OpenPose people by their joint count (core.formats.OPENPOSE_FORMATS: 18 is
    --model_pose COCO, 25 BODY_25, the default model), else None. The experimental BODY_25B has 25 too,
    in another order: nothing in the file tells it, so body25 is read and `repnet lift` says so
    (format_hints.alternatives_note); --format body25b reads it."""
    return OPENPOSE_FORMATS.get(len(people[0])) if people else None


def frame_number(path: Path) -> int | None:
    """The frame number in a file name: its last run of digits (OpenPose: video_000000000012_keypoints)."""
    digits = re.findall(r"\d+", path.stem)
    if not digits or len(digits[-1]) > 16:  # longer runs of digits are no frame number (MAX_FRAME)
        return None
    number = int(digits[-1])
    return number if number <= MAX_FRAME else None


def read_json(path: Path) -> Any:
    """The JSON value of a file; InputFileError naming the file when it is not JSON, is nested
    deeper than Python's parser goes, or cannot be read."""
    try:
        text = path.read_text()
        if not text.strip():
            raise InputFileError(f"{path}: the file is empty")
        return json.loads(text)
    except json.JSONDecodeError as err:
        raise InputFileError(f"{path}: not valid JSON: {err}") from None
    except RecursionError:
        raise InputFileError(f"{path}: the JSON is nested too deeply to read") from None
    except (OSError, ValueError) as err:
        raise InputFileError(f"{path}: {err}") from err
