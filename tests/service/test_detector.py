"""The bundled BlazePose detector on a real clip: it finds the person, its landmarks agree with
MediaPipe's own Python on the same frames, and it follows the person from frame to frame."""

from __future__ import annotations

import json
from pathlib import Path

import av
import numpy as np
import pytest

from repnet.core.formats import FORMATS
from repnet.runtime.blazepose import Roi
from repnet.runtime.detector import PoseDetector

VIDEO = Path(__file__).resolve().parents[1] / "fixtures" / "video"
CLIP = VIDEO / "street640.mp4"
NAMES = FORMATS["mediapipe33"].joint_names
AGREEMENT_PX = 2.0  # mean distance to MediaPipe's landmarks over the visible ones, at 640 px wide


@pytest.fixture(scope="module")
def frames() -> list[np.ndarray]:
    with av.open(str(CLIP)) as container:
        return [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]


@pytest.fixture(scope="module")
def detector() -> PoseDetector:
    return PoseDetector()


@pytest.fixture(scope="module")
def reference() -> dict:
    return json.loads((VIDEO / "street640.mediapipe.json").read_text())


def test_the_detector_finds_the_person_with_its_landmarks_in_the_frame(
    frames: list[np.ndarray], detector: PoseDetector
) -> None:
    height, width = frames[0].shape[:2]
    for image in frames:
        person = detector.single(image)
        assert person is not None and person.score > 0.9
        inside = ((person.points >= 0) & (person.points < [width, height])).all(axis=1)
        # her feet are at the frame's bottom edge: a heel may be placed a few px below it
        assert inside[: NAMES.index("left_knee")].all()
        assert (person.points >= 0).all() and (person.points < [width, 1.06 * height]).all()
        low, high = person.points.min(axis=0), person.points.max(axis=0)
        # the woman in white on the right: her box is about half the frame tall, in its right third
        assert 0.4 * height < high[1] - low[1] < 0.95 * height and low[0] > 0.6 * width


def test_landmarks_agree_with_mediapipes_own_python(
    frames: list[np.ndarray], detector: PoseDetector, reference: dict
) -> None:
    size = np.array([reference["width"], reference["height"]])
    errors = []
    for image, expected in zip(frames, reference["frames"], strict=True):
        person = detector.single(image)
        rows = np.array(expected["landmarks"])  # (33, 5) x, y normalised, z, visibility, presence
        assert person is not None
        visible = rows[:, 3] > 0.5
        errors.append(np.linalg.norm(person.points - rows[:, :2] * size, axis=1)[visible])
        np.testing.assert_allclose(person.visibility, rows[:, 3], atol=0.1)
    assert np.concatenate(errors).mean() <= AGREEMENT_PX


def test_each_stage_agrees_with_mediapipes_given_the_same_input(
    frames: list[np.ndarray], detector: PoseDetector, reference: dict
) -> None:
    """The detector's keypoints within 1 px of MediaPipe's; the landmark stage, given MediaPipe's own
    region, within 0.3 px on average (what is left is onnxruntime's and OpenCV's arithmetic)."""
    width, height = reference["width"], reference["height"]
    for image, expected in zip(frames, reference["frames"], strict=True):
        found = detector.detect(image, zoom=0)
        keypoints = np.array(expected["detection_keypoints"]) * [width, height]
        assert np.abs(found.keypoints[0] - keypoints).max() < 1.0
        x, y, w, _, rotation = expected["roi_from_detection"]
        person = detector.landmarks(image, Roi(x * width, y * height, w * width, rotation))
        rows = np.array(expected["landmarks"])
        visible = rows[:, 3] > 0.5
        assert np.linalg.norm(person.points - rows[:, :2] * [width, height], axis=1)[visible].mean() < 0.3


def test_left_and_right_are_the_references(
    frames: list[np.ndarray], detector: PoseDetector, reference: dict
) -> None:
    # seen from behind, her left shoulder and hip are on the image's left
    person = detector.single(frames[0])
    rows = np.array(reference["frames"][0]["landmarks"])
    assert person is not None
    for side in ("shoulder", "hip"):
        left, right = NAMES.index(f"left_{side}"), NAMES.index(f"right_{side}")
        assert person.points[left, 0] < person.points[right, 0]
        assert rows[left, 0] < rows[right, 0]


def test_tracking_follows_the_person_without_running_the_detector_again(
    frames: list[np.ndarray], reference: dict
) -> None:
    detector = PoseDetector(redetect_every=0)
    calls = []
    detect = detector.detect
    detector.detect = lambda image: calls.append(1) or detect(image)  # type: ignore[method-assign]
    tracked = [detector.track(image) for image in frames]
    assert [len(people) for people in tracked] == [1] * len(frames) and calls == [1]
    size = np.array([reference["width"], reference["height"]])
    for people, expected in zip(tracked, reference["frames"], strict=True):
        rows = np.array(expected["landmarks"])
        visible = rows[:, 3] > 0.5
        assert np.linalg.norm(people[0].points - rows[:, :2] * size, axis=1)[visible].mean() < 6.0


def test_a_blank_frame_has_no_person(detector: PoseDetector) -> None:
    blank = np.full((360, 640, 3), 90, np.uint8)
    assert detector.single(blank) is None
    fresh = PoseDetector()
    assert fresh.track(blank) == []
