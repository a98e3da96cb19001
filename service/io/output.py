"""`repnet lift -o FILE`: the lifted poses written by the file's suffix (.json, .npz, .csv, .bvh)."""

from __future__ import annotations

import csv
import glob
import hashlib
import io
import json
import re
import stat
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from repnet.client.result import LiftResult
from repnet.core.formats import FORMATS, to_model_joints
from repnet.io.bvh import CAMERA_TO_BVH, solve_motion, write_bvh
from repnet.io.poses import InputFileError, Poses

DEFAULT_BVH_FPS = 30.0  # the frame time of a BVH whose poses give no frame rate


@dataclass(frozen=True)
class Lifted:
    """What `repnet lift` writes: the JSON document, the results and the poses they are of."""

    document: dict[str, Any]  # the .json output (model_id, format, temporal, fps, joints, poses, ...)
    results: Sequence[LiftResult]
    poses: Poses


def check_output(path: Path, overwrite: bool = False) -> None:
    """InputFileError unless `path`'s suffix names a writer, its folder exists and, unless
    `overwrite`, no file it would write exists (a .bvh: the per-person files beside it too): checked
    before lifting, so a long lift is not lost to a typo, nor an earlier output to a rerun. A device
    (`-o /dev/null`, `/dev/stdout`) takes the JSON whatever its name."""
    if is_device(path):
        return
    if path.suffix.lower() not in WRITERS:
        raise InputFileError(
            f"-o {path}: unknown output suffix {path.suffix or '(none)'!r}; expected one of "
            f"{', '.join(WRITERS)}"
        )
    if not path.parent.is_dir():
        raise InputFileError(f"-o {path}: the folder {path.parent} does not exist")
    if path.is_dir():
        raise InputFileError(f"-o {path}: a folder, not a file")
    if overwrite:
        return
    found = [path] if path.exists() else []
    if path.suffix.lower() == ".bvh":
        found += sorted(path.parent.glob(f"{glob.escape(path.stem)}.track-*{path.suffix}"))
        found += sorted(path.parent.glob(f"{glob.escape(path.stem)}.person-*{path.suffix}"))
    if found:
        raise InputFileError(f"-o {path}: {found[0]} exists; --overwrite replaces it")


def is_device(path: Path) -> bool:
    """Whether `path` is a character device or a pipe (/dev/null, /dev/stdout, a FIFO): written as a
    stream, never refused for existing."""
    try:
        mode = path.stat().st_mode
    except OSError:
        return False
    return stat.S_ISCHR(mode) or stat.S_ISFIFO(mode)


def file_key(key: str) -> str:
    """A person's key (track-<id> or person-<i>) as a file name part: characters other than letters,
    digits, '.', '_' and '-' become '_' (a track id is the input's: '../x' or a NUL must not reach a
    path), with a short hash of the key when anything was replaced, so two ids stay two files."""
    safe = re.sub(r"[^A-Za-z0-9._-]", "_", key)
    if safe == key:
        return key
    return f"{safe}-{hashlib.sha256(key.encode()).hexdigest()[:8]}"


def write_output(path: Path, lifted: Lifted) -> list[Path]:
    """Write `lifted` as `path`'s suffix says, replacing what is there (the caller's check_output said
    whether it may); the files written (a .bvh: one per person)."""
    check_output(path, overwrite=True)
    return WRITERS[".json" if is_device(path) else path.suffix.lower()](path, lifted)


def _write_json(path: Path, lifted: Lifted) -> list[Path]:
    path.write_text(json.dumps(lifted.document, allow_nan=False))
    return [path]


def _column(values: list[Any]) -> np.ndarray:
    """One reply field over all poses as an array: None becomes NaN (numbers) or "" (strings)."""
    if all(isinstance(v, str) or v is None for v in values):
        return np.array(["" if v is None else v for v in values], dtype=str)
    if any(isinstance(v, tuple) for v in values):  # warnings: one joined string per pose
        return np.array(["; ".join(v) for v in values], dtype=str)
    shape = next((np.shape(v) for v in values if v is not None), ())
    return np.array([np.full(shape, np.nan) if v is None else v for v in values])


def _write_npz(path: Path, lifted: Lifted) -> list[Path]:
    """Every reply field as an (N, ...) array under its own name, beside what `repnet lift` reads
    back (keypoints (N, J, 2) with NaN for missing joints, confidence, format, fps) and frame,
    person, joints, parents, model_id."""
    doc, poses = lifted.document, lifted.poses
    arrays: dict[str, Any] = {
        name: _column([getattr(r, name) for r in lifted.results]) for name in LiftResult.pose_fields()
    }
    arrays.update(
        keypoints=poses.points,
        frame=poses.frame,
        person=poses.person,
        format=doc["format"],
        joints=np.array(doc["joints"]),
        parents=np.array(doc["parents"]),
        model_id=doc["model_id"],
    )
    if poses.confidence is not None:
        arrays["confidence"] = poses.confidence
    if doc.get("fps") is not None:
        arrays["fps"] = float(doc["fps"])
    np.savez_compressed(path, **arrays)
    return [path]


CSV_HEADER = (
    "frame",
    "track_id",
    "person",
    "joint",
    "x_mm",
    "y_mm",
    "z_mm",
    "x_camera_m",
    "y_camera_m",
    "z_camera_m",
    "input_x_px",
    "input_y_px",
    "visible",
    "imputed",
)


def input_points(lifted: Lifted) -> tuple[np.ndarray, np.ndarray]:
    """Each pose's input point at each model joint: (N, 17, 2) px and (N, 17) whether it has one.
    The input is in the file's format (coco17's 17 joints are not the model's 17): its points are
    mapped onto the model's joints by the format's table, a derived joint (coco17's pelvis) the
    midpoint of its sources where both are there."""
    points = lifted.poses.points  # (N, K, 2), what the document's `input` echoes
    present = np.isfinite(points).all(axis=-1)  # the echo's non-null joints
    points17, visible17, _, _ = to_model_joints(FORMATS[lifted.document["format"]], points, present)
    return points17, visible17


def _write_csv(path: Path, lifted: Lifted) -> list[Path]:
    """One row per pose per joint: x, y, z the pose in the camera's orientation (pose_3d_camera, mm,
    pelvis at the origin); *_camera_m the joint in camera coordinates (root_camera_m + the pose), empty
    without intrinsics; the input point at that model joint (input_points; empty where the input has
    none) and the joint's flags."""
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(CSV_HEADER)
    joints = lifted.document["joints"]
    points17, has_point = input_points(lifted)
    for i, result in enumerate(lifted.results):
        frame, person = int(lifted.poses.frame[i]), int(lifted.poses.person[i])
        placed = (
            None if result.root_camera_m is None else result.root_camera_m + result.pose_3d_camera / 1000.0
        )
        for j, name in enumerate(joints):
            at = ("", "", "") if placed is None else tuple(f"{v:.5f}" for v in placed[j])
            # float32 written shortest: a point sent as 393.6 reads 393.6
            point = (
                tuple(np.format_float_positional(v, trim="-") for v in points17[i, j])
                if has_point[i, j]
                else ("", "")
            )
            writer.writerow(
                [
                    frame,
                    result.track_id or "",
                    person,
                    name,
                    *(f"{v:.2f}" for v in result.pose_3d_camera[j]),
                    *at,
                    *point,
                    int(result.visible[j]),
                    int(result.imputed[j]),
                ]
            )
    path.write_text(out.getvalue())
    return [path]


def people_of(lifted: Lifted) -> dict[str, list[int]]:
    """The poses of each person in frame order: by track where the results have tracks, else by
    the person's index in its frame."""
    groups: dict[str, list[int]] = {}
    for i, result in enumerate(lifted.results):
        key = f"track-{result.track_id}" if result.track_id else f"person-{int(lifted.poses.person[i])}"
        groups.setdefault(key, []).append(i)
    return {k: sorted(v, key=lambda i: int(lifted.poses.frame[i])) for k, v in groups.items()}


def person_positions(results: Sequence[LiftResult], frames: np.ndarray) -> np.ndarray:
    """(T, 17, 3) one person's joints in metres, BVH axes, one row per frame from the first to the
    last (a frame without a pose repeats the one before): pose_3d_camera, at root_camera_m when every
    pose has one, else with the root at the origin."""
    placed = all(r.root_camera_m is not None for r in results)
    rows = [
        r.pose_3d_camera / 1000.0 + (r.root_camera_m if placed and r.root_camera_m is not None else 0.0)
        for r in results
    ]
    span = np.arange(int(frames.min()), int(frames.max()) + 1)
    latest = np.searchsorted(frames, span, side="right") - 1  # the last pose at or before each frame
    return np.asarray(np.stack(rows)[latest] @ CAMERA_TO_BVH.T, dtype=np.float64)


def _write_bvh(path: Path, lifted: Lifted) -> list[Path]:
    """One BVH per person (path itself for one person, else path.<track-id|person-i>.bvh)."""
    fps = lifted.document.get("fps") or DEFAULT_BVH_FPS
    groups = people_of(lifted)
    written = []
    for key, rows in groups.items():
        results = [lifted.results[i] for i in rows]
        frames = lifted.poses.frame[rows].astype(np.int64)
        if len(np.unique(frames)) != len(frames):
            raise InputFileError(f"{key}: several poses in one frame; give each person a track_id")
        target = path if len(groups) == 1 else path.with_name(f"{path.stem}.{file_key(key)}{path.suffix}")
        target.write_text(write_bvh(solve_motion(person_positions(results, frames), 1.0 / float(fps))))
        written.append(target)
    return written


WRITERS: dict[str, Callable[[Path, Lifted], list[Path]]] = {
    ".json": _write_json,
    ".npz": _write_npz,
    ".csv": _write_csv,
    ".bvh": _write_bvh,
}
