"""Detector files in each tool's own layout (tests/fixtures/detectors/), made from the tests' hand-made
person (conftest.POSE_3D) seen by a pinhole camera, with the poses each must be read as. The layouts
and their sources are in tests/fixtures/detectors/README.md. Regenerate: python -m
tests.service.detector_files"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from repnet.core.formats import FORMATS, MODEL_JOINTS, from_model_joints
from tests.conftest import POSE_3D, project
from tests.service.page_examples import ALIASES, OFFSETS_MM

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures" / "detectors"
IMAGE_SIZE = (1024.0, 1000.0)  # the image YOLO labels and MediaPipe landmarks are normalised by, px
COCO17 = ("nose", "left_eye", "right_eye", "left_ear", "right_ear", "left_shoulder", "right_shoulder",
          "left_elbow", "right_elbow", "left_wrist", "right_wrist", "left_hip", "right_hip", "left_knee",
          "right_knee", "left_ankle", "right_ankle")  # fmt: skip
# Halpe-26 (AlphaPose): COCO-17, then head (top), neck, hip (mid), big toes, small toes and heels.
HALPE26 = (*COCO17, "head@halpe", "neck@halpe", "hip@halpe", "left_big_toe", "right_big_toe",
           "left_small_toe", "right_small_toe", "left_heel", "right_heel")  # fmt: skip
# COCO-WholeBody's feet, in its order (foot_kpts).
FEET = ("left_big_toe", "left_small_toe", "left_heel", "right_big_toe", "right_small_toe", "right_heel")
HALPE_ALIASES = {"head@halpe": "head", "neck@halpe": "thorax", "hip@halpe": "pelvis"}


def _points_3d() -> dict[str, np.ndarray]:
    """The person's joints (mm) by name: the model's, COCO's face and the feet."""
    points = {name: POSE_3D[j] for j, name in enumerate(MODEL_JOINTS)}
    for name, (base, offset) in OFFSETS_MM.items():
        points[name] = points[base] + np.array(offset, dtype=np.float64)
    return points


def person(names: tuple[str, ...], yaw: float, shift: float = 0.0) -> np.ndarray:
    """(K, 2) px: the person turned by `yaw` in the joints `names`, moved `shift` px to the right."""
    points = _points_3d()
    alias = {**ALIASES, **HALPE_ALIASES}
    chosen = np.stack([points[alias.get(n, n)] for n in names])
    return np.round(project(chosen, yaw) + [shift, 0.0], 1)


def wholebody(yaw: float) -> np.ndarray:
    """(133, 2) px: body 17, feet 6, a ring of 68 face points round the nose, 21 points per hand
    running down from its wrist."""
    points = _points_3d()
    nose = points[ALIASES["nose"]]
    angles = np.linspace(0, 2 * np.pi, 68, endpoint=False)
    face = nose + np.stack([60 * np.cos(angles), 70 * np.sin(angles), np.zeros(68)], axis=1)
    hands = [points[w] + np.stack([np.zeros(21), 8.0 * np.arange(21), np.zeros(21)], axis=1)
             for w in ("left_wrist", "right_wrist")]  # fmt: skip
    body = np.stack([points[ALIASES.get(n, n)] for n in (*COCO17, *FEET)])
    return np.round(project(np.concatenate([body, face, *hands]), yaw), 1)


def mediapipe(yaw: float) -> np.ndarray:
    """(33, 2) px: MediaPipe's landmarks where the model has the joint, else the nose's point."""
    landmarks, found = from_model_joints(FORMATS["mediapipe33"], project(POSE_3D, yaw)[None])
    return np.where(found[0][:, None], landmarks[0], landmarks[0, 0]).round(1)


@dataclass
class Expected:
    """What a file must be read as: poses (N, K, 2) px (NaN: missing), confidence (N, K) or None,
    format, frames, people and labels."""

    points: np.ndarray
    confidence: np.ndarray | None
    format: str
    frame: list[int]
    person: list[int]
    label: list[str]
    image_size: tuple[float, float] | None = None  # the size to read the file with (normalised x, y)
    files: dict[str, str] = field(default_factory=dict)  # file name -> text


def _scores(k: int, top: float = 0.95) -> np.ndarray:
    return np.linspace(top, 0.6, k).round(2)


def mmpose_video() -> Expected:
    """MMPoseInferencer(pred_out_dir=...) on a video: [{frame_id, instances}], a frame with nobody."""
    poses = [person(COCO17, 0.0), person(COCO17, 20.0), person(COCO17, 20.0, 300.0)]
    scores = np.stack([_scores(17), _scores(17, 0.9), _scores(17, 0.85)])
    scores[0, 5:7] = [1.0863, 1.112]  # RTMPose's SimCC maxima pass 1 (mmpose issues 2755, 3122)
    conf = np.minimum(scores, 1.0)  # read as sure

    def instance(p: np.ndarray, c: np.ndarray) -> dict[str, Any]:
        box = [float(p[:, 0].min()), float(p[:, 1].min()), float(p[:, 0].max()), float(p[:, 1].max())]
        return {"keypoints": p.tolist(), "keypoint_scores": c.tolist(), "bbox": [box], "bbox_score": 0.97}

    frames = [
        [instance(poses[0], scores[0])],
        [],
        [instance(p, c) for p, c in zip(poses[1:], scores[1:], strict=True)],
    ]
    data = [{"frame_id": i, "instances": instances} for i, instances in enumerate(frames)]
    labels = ["frame_id 0, instance 0", "frame_id 2, instance 0", "frame_id 2, instance 1"]
    return Expected(np.stack(poses), conf, "coco17", [0, 2, 2], [0, 0, 1], labels,
                    files={"mmpose_video.json": json.dumps(data, indent=2)})  # fmt: skip


def mmpose_image() -> Expected:
    """MMPoseInferencer(pred_out_dir=...) on one image: the instances list, Halpe-26 joints."""
    pose, conf = person(HALPE26, -30.0), _scores(26)
    box = [[300.0, 100.0, 700.0, 900.0]]
    data = [{"keypoints": pose.tolist(), "keypoint_scores": conf.tolist(), "bbox": box, "bbox_score": 0.93}]
    return Expected(pose[None], conf[None], "halpe26", [0], [0], ["instance 0"],
                    files={"mmpose_image.json": json.dumps(data, indent=2)})  # fmt: skip


def _yolo_box(p: np.ndarray) -> dict[str, float]:
    return {"x1": float(p[:, 0].min()), "y1": float(p[:, 1].min()), "x2": float(p[:, 0].max()),
            "y2": float(p[:, 1].max())}  # fmt: skip


def yolo_summary() -> Expected:
    """Ultralytics Results.to_json() of one image with two people (pixels: normalize=False)."""
    poses = np.stack([person(COCO17, 10.0), person(COCO17, -10.0, -250.0)])
    conf = np.stack([_scores(17, 0.99), _scores(17, 0.8)])
    data = [{"name": "person", "class": 0, "confidence": 0.91 - 0.1 * k, "box": _yolo_box(p),
             "keypoints": {"x": p[:, 0].tolist(), "y": p[:, 1].tolist(), "visible": c.tolist()}}
            for k, (p, c) in enumerate(zip(poses, conf, strict=True))]  # fmt: skip
    return Expected(poses, conf, "coco17", [0, 0], [0, 1], ["detection 0", "detection 1"],
                    files={"yolo_summary.json": json.dumps(data, indent=2)})  # fmt: skip


def _yolo_line(p: np.ndarray, c: np.ndarray | None, tail: tuple[float, ...] = ()) -> tuple[str, np.ndarray]:
    """A save_txt line (`%g` values, as Ultralytics writes them) and the normalised points it holds."""
    xy = np.array([float(f"{v:g}") for v in (p / IMAGE_SIZE).ravel()]).reshape(-1, 2)
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    box = [*((lo + hi) / 2), *(hi - lo)]
    joints = xy if c is None else np.concatenate([xy, c[:, None]], axis=1)
    values = (0, *box, *joints.ravel(), *tail)
    return ("%g " * len(values)).rstrip() % values, xy


def yolo_labels() -> Expected:
    """save_txt label files of a clip (clip_<frame>.txt): frame 0 one person with visibility, frame 2
    two people, the second with save_conf and a track id; x, y normalised to the image."""
    first, second, third = person(COCO17, 0.0), person(COCO17, 15.0), person(COCO17, 15.0, 280.0)
    conf = np.stack([_scores(17), _scores(17, 0.9), _scores(17, 0.7)])
    lines = [_yolo_line(first, conf[0]), _yolo_line(second, conf[1]), _yolo_line(third, conf[2], (0.88, 7))]
    points = np.stack([xy for _, xy in lines]) * IMAGE_SIZE
    files = {"clip_0.txt": lines[0][0] + "\n", "clip_2.txt": lines[1][0] + "\n" + lines[2][0] + "\n"}
    labels = ["clip_0.txt line 1", "clip_2.txt line 1", "clip_2.txt line 2"]
    return Expected(points, conf, "coco17", [0, 2, 2], [0, 0, 1], labels, IMAGE_SIZE,
                    files={f"yolo_labels/{k}": v for k, v in files.items()})  # fmt: skip


def _landmarks(p: np.ndarray, visibility: np.ndarray, js: bool) -> list[dict[str, float]]:
    rows = []
    for (x, y), v in zip((p / IMAGE_SIZE).tolist(), visibility.tolist(), strict=True):
        mark = {"x": x, "y": y, "z": -0.1, "visibility": v}
        rows.append(mark if js else {**mark, "presence": 0.99})
    return rows


def mediapipe_results() -> Expected:
    """PoseLandmarker results as JSON: Python's (pose_landmarks, with presence) for two frames, and the
    JS Tasks API's ({landmarks, worldLandmarks}) for one; world landmarks are never read."""
    poses = np.stack([mediapipe(30.0), mediapipe(40.0)])
    conf = np.stack([np.full(33, 0.9), _scores(33)])
    world = [[{"x": 0.1, "y": -0.5, "z": 0.05, "visibility": 0.9}] * 33]
    python = [{"pose_landmarks": [_landmarks(p, c, js=False)], "pose_world_landmarks": world}
              for p, c in zip(poses, conf, strict=True)]  # fmt: skip
    js = {"landmarks": [_landmarks(poses[0], conf[0], js=True)], "worldLandmarks": world}
    points = (
        np.stack([np.array([[m["x"], m["y"]] for m in r["pose_landmarks"][0]]) for r in python]) * IMAGE_SIZE
    )
    return Expected(points, conf, "mediapipe33", [0, 1], [0, 0], ["result 0, pose 0", "result 1, pose 0"],
                    IMAGE_SIZE, files={"mediapipe_python.json": json.dumps(python, indent=1),
                                       "mediapipe_js.json": json.dumps(js, indent=1)})  # fmt: skip


def alphapose() -> Expected:
    """alphapose-results.json (Halpe-26 model): frames by the image file's number, `idx` per person."""
    poses = np.stack([person(HALPE26, 0.0), person(HALPE26, 25.0), person(HALPE26, 25.0, 320.0)])
    conf = np.stack([_scores(26), _scores(26, 0.9), _scores(26, 0.8)])
    images = ["0.jpg", "1.jpg", "1.jpg"]
    data = [{"image_id": image, "category_id": 1,
             "keypoints": np.concatenate([p, c[:, None]], axis=1).ravel().tolist(), "score": 2.9 - k / 2,
             "box": [200.0, 100.0, 400.0, 800.0], "idx": [k + 1]}
            for k, (image, p, c) in enumerate(zip(images, poses, conf, strict=True))]  # fmt: skip
    labels = ["image_id '0.jpg'", "image_id '1.jpg'", "image_id '1.jpg'"]
    return Expected(poses, conf, "halpe26", [0, 1, 1], [0, 0, 1], labels,
                    files={"alphapose-results.json": json.dumps(data)})  # fmt: skip


def coco_wholebody() -> Expected:
    """A COCO-WholeBody annotation file: body `keypoints` plus foot, face and hand parts (x, y, v
    flags); the right hand not annotated (all 0)."""
    pose = wholebody(-15.0)
    flags = np.full(133, 2.0)
    flags[112:] = 0.0  # the right hand: 0, 0, 0
    flat = np.concatenate([np.where(flags[:, None] > 0, pose, 0.0), flags[:, None]], axis=1)
    parts = {"keypoints": flat[:17], "foot_kpts": flat[17:23], "face_kpts": flat[23:91],
             "lefthand_kpts": flat[91:112], "righthand_kpts": flat[112:]}  # fmt: skip
    annotation = {"image_id": 785, "id": 442619, "category_id": 1, "iscrowd": 0, "num_keypoints": 17,
                  "bbox": [280.8, 44.0, 218.7, 346.7], "face_valid": True, "lefthand_valid": True,
                  "righthand_valid": False, "foot_valid": True,
                  **{k: v.ravel().tolist() for k, v in parts.items()}}  # fmt: skip
    data = {"images": [{"id": 785, "file_name": "000000000785.jpg", "width": 640, "height": 425}],
            "annotations": [annotation], "categories": [{"id": 1, "name": "person"}]}  # fmt: skip
    points = np.where(flags[:, None] > 0, pose, np.nan)[None]
    return Expected(points, None, "wholebody133", [785], [0], ["image_id 785, id 442619"],
                    files={"coco_wholebody.json": json.dumps(data)})  # fmt: skip


def openpose_coco18() -> Expected:
    """One OpenPose frame of the COCO-18 model (--model_pose COCO): COCO's joints with a neck, in
    OpenPose's order (nose, neck, right arm, left arm, right leg, left leg, eyes, ears)."""
    order = ("nose", "thorax", "right_shoulder", "right_elbow", "right_wrist", "left_shoulder", "left_elbow",
             "left_wrist", "right_hip", "right_knee", "right_ankle", "left_hip", "left_knee", "left_ankle",
             "right_eye", "left_eye", "right_ear", "left_ear")  # fmt: skip
    pose, conf = person(order, 5.0), _scores(18)
    flat = np.concatenate([pose, conf[:, None]], axis=1).ravel().tolist()
    data = {"version": 1.3, "people": [{"person_id": [-1], "pose_keypoints_2d": flat}]}
    name = "openpose_coco18_000000000000_keypoints.json"
    return Expected(pose[None], conf[None], "coco18", [0], [0], [name], files={name: json.dumps(data)})


BUILDERS = {"mmpose video": mmpose_video, "mmpose image": mmpose_image, "yolo summary": yolo_summary,
            "yolo labels": yolo_labels, "mediapipe results": mediapipe_results, "alphapose": alphapose,
            "coco wholebody": coco_wholebody, "openpose coco18": openpose_coco18}  # fmt: skip


def write_fixtures(folder: Path = FIXTURES) -> None:
    for build in BUILDERS.values():
        for name, text in build().files.items():
            (folder / name).parent.mkdir(parents=True, exist_ok=True)
            (folder / name).write_text(text)


if __name__ == "__main__":
    write_fixtures()
    print(f"wrote {FIXTURES}")
