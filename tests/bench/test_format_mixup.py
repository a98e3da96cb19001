"""bench.format_mixup without the Human3.6M data: its pipeline on the test person, its arguments."""

from __future__ import annotations

import numpy as np
import pytest

from bench.format_mixup import detector_poses, frames, markdown, parse_args, send
from repnet.runtime.lifter import Lifter
from tests.conftest import POSE_3D, project


def test_send_flags_poses_under_the_wrong_label_only(trained: Lifter) -> None:
    h36m = np.stack([project(POSE_3D, yaw) for yaw in range(-90, 91, 30)])  # (7, 17, 2)
    coco, present = detector_poses("coco17", h36m)
    assert send(trained, coco, present, "h36m17")["fired"].all()
    assert not send(trained, coco, present, "coco17")["fired"].any()
    everything = np.ones(h36m.shape[:2], bool)
    assert send(trained, h36m, everything, "coco17")["fired"].all()
    out = send(trained, h36m, everything, "h36m17")
    assert not out["fired"].any() and out["relative"].shape == (7,) and (out["height"] < 0).all()


def test_markdown_gives_the_rates_against_the_targets() -> None:
    row = {
        "truth": "coco17", "label": "h36m17", "poses": 10, "fired": 0.9, "fired_count": 9,
        "reprojection_only": 0.9, "geometry_only": 0.8, "relative_p": [0.1, 0.2, 0.3, 0.4, 0.5],
    }  # fmt: skip
    summary = {"fired": {"fires_when_wrong": 0.9, "fires_when_right": 0.001}}
    text = markdown({
        "command": "c", "dataset": "d", "frame_step": 1, "poses_per_format": 10, "model_id": "m",
        "plausibility": False, "rows": [row], "summary": summary, "threshold": 0.25,
    })  # fmt: skip
    assert "| coco17 | h36m17 | 10 | 90.000% (9) |" in text
    assert "fires on 90.000% of wrongly labelled poses (target >= 99 %) and 0.100%" in text


def test_subjects_must_all_be_training_or_all_test_subjects() -> None:
    assert parse_args(["--subjects", "S1,S5"]).subjects == ["S1", "S5"]
    with pytest.raises(SystemExit):
        parse_args(["--subjects", "S1,S9"])


def test_frame_steps_read_as_english() -> None:
    assert [frames(n) for n in (1, 2, 3, 10, 12, 22)] == [
        "every frame", "every 2nd frame", "every 3rd frame", "every 10th frame", "every 12th frame",
        "every 22nd frame",
    ]  # fmt: skip
