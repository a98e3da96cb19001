"""The page's bundled example poses (service/static/examples.json), made from the tests' hand-made
person (conftest.POSE_3D) seen by a pinhole camera. Regenerate: python -m tests.service.page_examples"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from repnet.core.formats import FORMATS, MODEL_JOINTS
from repnet.core.inputs import EXAMPLE_KEYPOINTS
from repnet.server.http.page import STATIC_DIR
from tests.conftest import POSE_3D, project

EXAMPLES_PATH = STATIC_DIR / "examples.json"
# Detector joints that the model has under another name, and face and foot points around the model's.
ALIASES = {"mid_hip": "pelvis", "neck@body25": "thorax", "nose": "neck", "upper_neck": "neck",
           "head_top": "head"}  # fmt: skip
OFFSETS_MM = {
    "left_eye": ("neck", [35, -45, -30]), "right_eye": ("neck", [-35, -45, -30]),
    "left_ear": ("neck", [75, -35, 40]), "right_ear": ("neck", [-75, -35, 40]),
    "left_big_toe": ("left_ankle", [20, 45, -130]), "left_small_toe": ("left_ankle", [60, 45, -110]),
    "left_heel": ("left_ankle", [0, 55, 40]), "right_big_toe": ("right_ankle", [-20, 45, -130]),
    "right_small_toe": ("right_ankle", [-60, 45, -110]), "right_heel": ("right_ankle", [0, 55, 40]),
}  # fmt: skip


def detector_pose(fmt: str, yaw_deg: float) -> np.ndarray:
    """(K, 2) px: the person turned by yaw_deg, in the joints of format `fmt`."""
    points = {name: POSE_3D[j] for j, name in enumerate(MODEL_JOINTS)}
    for name, (base, offset) in OFFSETS_MM.items():
        points[name] = points[base] + np.array(offset, dtype=np.float64)
    names = [ALIASES.get(f"{n}@{fmt}", ALIASES.get(n, n)) for n in FORMATS[fmt].joint_names]
    return np.round(project(np.stack([points[n] for n in names]), yaw_deg), 1)


def build_examples() -> list[dict[str, Any]]:
    coco = detector_pose("coco17", 60.0)
    scores = np.linspace(0.95, 0.6, len(coco)).round(2)
    coco_flat = np.concatenate([coco, scores[:, None]], axis=1).ravel().tolist()
    mpii = detector_pose("mpii16", -20.0).tolist()
    mpii[FORMATS["mpii16"].joint_names.index("left_wrist")] = None
    frames = []
    for yaw in range(0, 360, 10):
        body = detector_pose("body25", float(yaw))
        flat = np.concatenate([body, np.ones((len(body), 1))], axis=1).ravel().tolist()
        frames.append({"version": 1.3, "people": [{"person_id": [-1], "pose_keypoints_2d": flat}]})
    return [
        {"name": "Standing, mid-stride (h36m17, a POST /lift body)",
         "data": {"poses": [{"keypoints": EXAMPLE_KEYPOINTS}], "format": "h36m17"}},
        {"name": "Turned 60° (COCO-17 detector result with scores)",
         "data": [{"image_id": 1, "category_id": 1, "keypoints": coco_flat, "score": 0.93}]},
        {"name": "Left wrist not found (MPII-16, one pose)", "data": {"keypoints": mpii, "format": "mpii16"}},
        {"name": "Turning on the spot (OpenPose BODY_25, 36 frames)", "fps": 12, "data": frames},
    ]  # fmt: skip


def write_examples(path: Path = EXAMPLES_PATH) -> None:
    path.write_text(json.dumps(build_examples(), separators=(",", ":")) + "\n")


if __name__ == "__main__":
    write_examples()
    print(f"wrote {EXAMPLES_PATH}")
