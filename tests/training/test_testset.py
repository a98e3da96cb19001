"""The S9/S11 test frames: action names, detections mapped, trimmed or refused."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from repnet.train import data, testset


def test_action_name_merges_the_takes_of_an_action() -> None:
    assert [testset.action_name(s) for s in ("Walking 1", "WalkDog", "Eating 2", "Photo 1")] == [
        "Walking", "WalkDog", "Eating", "Photo",
    ]  # fmt: skip


def test_detection_length_mismatch_is_trimmed_or_rejected(h36m_dir: Path) -> None:
    poses, cameras = data.load_poses(h36m_dir, "test"), data.load_cameras(h36m_dir)
    long = {"S9/Walking": np.zeros((100, 17, 3), dtype=np.float32)}
    det = {f"S9/Walking/{c}": np.ones((99, 16, 2), dtype=np.float32) for c in data.CAMERAS}
    test = testset.build_test_set(long, cameras, det)
    assert len(test.gt) == 4 * 99 and len(test.notes) == 4
    det = {f"S9/Walking/{c}": np.ones((len(poses["S9/Walking"]) // 2, 16, 2), "f4") for c in data.CAMERAS}
    with pytest.raises(ValueError, match="expected 9 frames"):
        testset.build_test_set({"S9/Walking": poses["S9/Walking"]}, cameras, det)


def test_selection_keeps_the_named_subjects_and_actions_and_refuses_none() -> None:
    poses = {key: np.zeros((2, 17, 3), np.float32) for key in ("S9/Walking 1", "S9/Eating", "S11/Walking")}
    assert set(testset.select_sequences(poses, ["S9"], [])) == {"S9/Walking 1", "S9/Eating"}
    assert set(testset.select_sequences(poses, ["S9", "S11"], ["Walking"])) == {"S9/Walking 1", "S11/Walking"}
    with pytest.raises(ValueError, match="no test sequence"):
        testset.select_sequences(poses, ["S1"], [])
