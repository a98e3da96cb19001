"""The 2D pose detector of `repnet video`: BlazePose (MediaPipe Pose, the full landmark model) run by
onnxruntime, following several people through a clip by their regions of interest.

MediaPipe's Pose follows one person: it runs the detector until it finds someone, then takes each
frame's region from the previous frame's landmarks, and runs the detector again only when the
landmark model loses the person (pose_landmark_cpu.pbtxt). PoseDetector keeps that region per person:
the detector runs on the first frame, every `redetect_every` frames and on any frame where a person
was lost; a detection is a new person when no region followed already overlaps it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from repnet.runtime.blazepose import (
    DETECTOR_SIZE,
    LANDMARK_SIZE,
    Detections,
    Landmarks,
    Roi,
    alignment_roi,
    crop,
    decode_detections,
    decode_landmarks,
    detector_views,
    iou,
    merge_detections,
)
from repnet.runtime.session import SessionOptions, open_session

DETECTOR_MODELS = Path(__file__).resolve().parents[1] / "models" / "detector"
DETECTION_MODEL = DETECTOR_MODELS / "pose_detection.onnx"
LANDMARK_MODEL = DETECTOR_MODELS / "pose_landmark_full.onnx"
MIN_PRESENCE = 0.5  # the pose flag's threshold: below it the person is lost (min_tracking_confidence)
SAME_PERSON_IOU = 0.4  # a detection overlapping a followed region by more is that person


@dataclass
class _Followed:
    """A person followed from frame to frame: the region of the next frame."""

    roi: Roi


@dataclass
class PoseDetector:
    """BlazePose's two models in one process (2 threads each by default: a video's frames run one
    after the other), and the people it follows through the frames given to `track`."""

    max_people: int = 4
    redetect_every: int = 10  # frames; 0: only when a person is lost or none is followed
    zoom: int = 1  # the detector's closer views of a frame (blazepose.detector_views)
    threads: int = 2
    detection_model: Path = DETECTION_MODEL
    landmark_model: Path = LANDMARK_MODEL
    _followed: list[_Followed] = field(default_factory=list, init=False)
    _frames: int = field(default=0, init=False)

    def __post_init__(self) -> None:
        options = SessionOptions(intra_op_threads=self.threads)
        self._detector = open_session(self.detection_model, options)
        self._landmarker = open_session(self.landmark_model, options)
        self._detector_input = self._detector.get_inputs()[0].name
        self._landmark_input = self._landmarker.get_inputs()[0].name

    def detect(self, image: np.ndarray, zoom: int | None = None) -> Detections:
        """The people the detector finds in an RGB frame (H, W, 3) uint8, best first: in the whole
        frame and its closer views up to `zoom` (default: the detector's; blazepose.detector_views)."""
        views = detector_views(image.shape[1], image.shape[0], self.zoom if zoom is None else zoom)
        found = []
        for view in views:
            tensor = crop(image, view, DETECTOR_SIZE, zero_border=True) * 2.0 - 1.0  # range [-1, 1]
            raw, logits = self._detector.run(None, {self._detector_input: tensor[None]})
            found.append(decode_detections(raw[0], logits[0], view))
        return merge_detections(found)

    def landmarks(self, image: np.ndarray, roi: Roi) -> Landmarks:
        """The landmark model's person in the ROI of an RGB frame."""
        tensor = crop(image, roi, LANDMARK_SIZE, zero_border=False)  # range [0, 1]
        raw, flag, heatmap = self._landmarker.run(None, {self._landmark_input: tensor[None]})
        return decode_landmarks(raw[0], float(flag.reshape(-1)[0]), heatmap[0], roi)

    def single(self, image: np.ndarray) -> Landmarks | None:
        """MediaPipe Pose's still-image mode: the best detection's landmarks, None when the detector
        finds no one or the landmark model says no person is there."""
        found = self.detect(image, zoom=0)
        if not len(found.scores):
            return None
        keypoints = found.keypoints[0]
        person = self.landmarks(image, alignment_roi(keypoints[0], keypoints[1]))
        return person if person.score >= MIN_PRESENCE else None

    def track(self, image: np.ndarray) -> list[Landmarks]:
        """The people of the next frame of a clip: those followed from the previous frame, and the
        detector's new ones when it runs (the first frame, every `redetect_every`, after a loss),
        at most `max_people`, in the order they were first seen."""
        people: list[Landmarks] = []
        kept: list[_Followed] = []
        for person in self._followed:
            found = self.landmarks(image, person.roi)
            if found.score >= MIN_PRESENCE and not _overlaps(found, people):
                people.append(found)
                kept.append(_Followed(alignment_roi(found.auxiliary[0], found.auxiliary[1])))
        lost = len(kept) < len(self._followed)
        due = self.redetect_every > 0 and self._frames % self.redetect_every == 0
        if (lost or due or not kept) and len(kept) < self.max_people:
            self._add_new(image, people, kept)
        self._followed = kept
        self._frames += 1
        return people

    def _add_new(self, image: np.ndarray, people: list[Landmarks], kept: list[_Followed]) -> None:
        """The detector's people whom no followed region covers, while there is room."""
        found = self.detect(image)
        for keypoints in found.keypoints:
            if len(kept) >= self.max_people:
                break
            roi = alignment_roi(keypoints[0], keypoints[1])
            if any(_roi_iou(roi, f.roi) > SAME_PERSON_IOU for f in kept):
                continue
            person = self.landmarks(image, roi)
            if person.score >= MIN_PRESENCE and not _overlaps(person, people):
                people.append(person)
                kept.append(_Followed(alignment_roi(person.auxiliary[0], person.auxiliary[1])))

    def reset(self) -> None:
        """Forget the people followed (a new clip)."""
        self._followed, self._frames = [], 0


def _box(points: np.ndarray) -> np.ndarray:
    """(4,) the bounding box xmin, ymin, xmax, ymax of (K, 2) points."""
    return np.concatenate([points.min(axis=0), points.max(axis=0)])


def _roi_iou(a: Roi, b: Roi) -> float:
    """The overlap of two ROIs' bounding boxes."""
    return float(iou(_box(a.corners()), _box(b.corners())[None])[0])


def _overlaps(person: Landmarks, people: list[Landmarks]) -> bool:
    """Whether the person's landmarks' box overlaps one of `people`'s by more than SAME_PERSON_IOU:
    two regions that converged on one person."""
    if not people:
        return False
    boxes = np.stack([_box(p.points) for p in people])
    return bool((iou(_box(person.points), boxes) > SAME_PERSON_IOU).any())
