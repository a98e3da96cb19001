"""bench.format_hints without the Human3.6M data: its pipeline on the test person, its arguments."""

from __future__ import annotations

import numpy as np
import pytest

from bench.format_hints import COUNT_HINTED, count_answer, hints, markdown, parse_args, row, warned
from repnet.core.formats import FORMATS, from_model_joints
from repnet.runtime.lifter import Lifter
from tests.conftest import POSE_3D, project


def test_hints_name_the_format_of_a_format_less_pose_and_nothing_under_its_own(trained: Lifter) -> None:
    h36m = np.stack([project(POSE_3D, yaw) for yaw in range(-90, 91, 30)])  # (7, 17, 2)
    told = {"mpii16": "mpii16", "coco18": "coco18", "body25": "body25 or body25b",
            "body25b": "body25 or body25b", "halpe26": "halpe26", "mediapipe33": "mediapipe33",
            "wholebody133": "wholebody133"}  # fmt: skip
    assert set(told) == set(COUNT_HINTED) and all(count_answer(name) == told[name] for name in told)
    for name in COUNT_HINTED:
        points, present = from_model_joints(FORMATS[name], h36m)
        assert hints(points.astype(np.float64), present, "h36m17") == [told[name]] * 7
        assert hints(points.astype(np.float64), present, name) == [""] * 7
    coco, present = from_model_joints(FORMATS["coco17"], h36m)
    assert hints(coco.astype(np.float64), present, "mpii16") == ["coco17"] * 7
    assert warned(trained, coco.astype(np.float64), present, "h36m17") == ["coco17"] * 7
    assert warned(trained, coco.astype(np.float64), present, "coco17") == [""] * 7


def test_rows_and_markdown_give_the_rates_against_the_targets() -> None:
    r = row("no format", "body25", "h36m17", ["body25", "body25", "", "mpii16"], "body25")
    assert (r["right"], r["right_count"], r["told_other"]) == (0.5, 2, ["", "mpii16"])
    summary = {"count_hint_right": 0.5, "right_labels_told_something": 0.0}
    text = markdown({"command": "c", "dataset": "d", "frame_step": 10, "poses_per_format": 4,
                     "model_id": "m", "rows": [r], "summary": summary})  # fmt: skip
    assert "| no format | body25 | h36m17 | 4 | 50.000% (2) | nothing, mpii16 |" in text
    assert "told the right format(s): 50.000% (target >= 99 %)" in text


def test_the_frame_step_must_be_positive() -> None:
    assert parse_args([]).frame_step == 10
    with pytest.raises(SystemExit):
        parse_args(["--frame-step", "0"])
