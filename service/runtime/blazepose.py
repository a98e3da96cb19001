"""BlazePose's pre- and post-processing: the detector's anchors, box decoding and weighted NMS,
the region of interest (ROI) a detection or the previous frame's landmarks give, the crop the models
read (OpenCV's warp, as MediaPipe's CPU path), and the 39 landmarks' decoding with their heatmap
refinement; numpy but for the crop.

Each step follows the graph configs and calculators of MediaPipe (github.com/google-ai-edge/mediapipe,
Apache-2.0), named in each function; the numbers are the configs'. Pixels everywhere: an ROI is a
square (centre, side, rotation) in the frame's pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

DETECTOR_SIZE = 224  # pose_detection_cpu.pbtxt: ImageToTensorCalculator 224 x 224
LANDMARK_SIZE = 256  # pose_landmark_by_roi_cpu.pbtxt: 256 x 256
HEATMAP_SIZE = 64  # pose_landmark_full's heatmap output (64, 64, 39)
LANDMARKS = 39  # tensors_to_pose_landmarks_and_segmentation.pbtxt: 33 of the pose + 2 auxiliary + 4 unused
POSE_LANDMARKS = 33
MIN_SCORE = 0.5  # TensorsToDetectionsCalculator min_score_thresh
NMS_IOU = 0.3  # NonMaxSuppressionCalculator min_suppression_threshold (INTERSECTION_OVER_UNION, WEIGHTED)
ROI_SCALE = 1.25  # RectTransformationCalculator scale_x, scale_y (square_long) of both ROI graphs
# RefineLandmarksFromHeatmapCalculator's window. The graph config says kernel_size 7, but MediaPipe
# 0.10.21's own Python is reproduced by the proto's default, 9: given its own ROI, our landmarks are
# 0.11 px from its with 9 and 0.70 px with 7 (mean on tests/fixtures/video, measured): 9.
REFINE_KERNEL = 9
REFINE_MIN_CONFIDENCE = 0.5  # its min_confidence_to_refine (the proto's default)


@dataclass(frozen=True)
class Roi:
    """A square region of the frame the landmark model reads: centre (px), side (px), rotation
    (radians, clockwise on screen: the image's y points down)."""

    x: float
    y: float
    size: float
    rotation: float

    def corners(self) -> np.ndarray:
        """(4, 2) px: the square's corners."""
        unit = np.array([[-0.5, -0.5], [0.5, -0.5], [0.5, 0.5], [-0.5, 0.5]])
        return self.to_frame(unit + 0.5)

    def to_frame(self, points: np.ndarray) -> np.ndarray:
        """(..., 2) points in [0, 1] of the ROI -> px of the frame (LandmarkProjectionCalculator:
        centred, rotated, scaled by the side, moved to the centre)."""
        c, s = np.cos(self.rotation), np.sin(self.rotation)
        d = (points - 0.5) * self.size
        x = c * d[..., 0] - s * d[..., 1]
        y = s * d[..., 0] + c * d[..., 1]
        return np.stack([x + self.x, y + self.y], axis=-1)


def ssd_anchors() -> np.ndarray:
    """(2254, 2) the detector's anchor centres in [0, 1] (SsdAnchorsCalculator with pose_detection_cpu's
    options: 5 layers of strides 8, 16, 32, 32, 32, aspect ratio 1 plus the interpolated scale, offset
    0.5, fixed anchor size: consecutive layers of one stride share a grid, 2 anchors each per cell)."""
    strides = (8, 16, 32, 32, 32)
    out = []
    layer = 0
    while layer < len(strides):
        same = 0
        while layer + same < len(strides) and strides[layer + same] == strides[layer]:
            same += 1
        cells = int(np.ceil(DETECTOR_SIZE / strides[layer]))
        ys, xs = np.meshgrid(np.arange(cells), np.arange(cells), indexing="ij")
        centres = np.stack([(xs + 0.5) / cells, (ys + 0.5) / cells], axis=-1).reshape(-1, 1, 2)
        out.append(np.repeat(centres, 2 * same, axis=1).reshape(-1, 2))
        layer += same
    return np.concatenate(out)  # (2254, 2)


ANCHORS = ssd_anchors()


@dataclass(frozen=True)
class Detections:
    """The detector's people in one frame, in px, best first."""

    boxes: np.ndarray  # (D, 4) xmin, ymin, xmax, ymax
    keypoints: np.ndarray  # (D, 4, 2): hip centre, full-body scale point, shoulder centre, upper-body point
    scores: np.ndarray  # (D,)


def letterbox(width: int, height: int) -> Roi:
    """The ROI the detector reads a whole frame through: the frame's centre, its longer side
    (ImageToTensorCalculator keep_aspect_ratio: the shorter side is padded evenly)."""
    return Roi(width / 2, height / 2, float(max(width, height)), 0.0)


def detector_views(width: int, height: int, zoom: int) -> list[Roi]:
    """The squares the detector reads a frame through: the whole frame (letterbox), then for each
    zoom level k = 1, 2.. squares of side (the shorter side) / 2**(k - 1) covering the frame with
    even overlaps. The detector reads 224 px: a small person in the whole frame is missed, and a
    closer view finds them (a departure from MediaPipe, which reads the whole frame only)."""
    views = [letterbox(width, height)]
    for level in range(1, zoom + 1):
        side = min(width, height) / 2 ** (level - 1)
        if side >= max(width, height):
            continue  # the whole frame already
        xs, ys = _spread(width, side), _spread(height, side)
        views += [Roi(float(x), float(y), float(side), 0.0) for y in ys for x in xs]
    return views


def _spread(length: int, side: float) -> np.ndarray:
    """The centres of the fewest squares of `side` that cover `length`, evenly spaced."""
    count = int(np.ceil(length / side - 1e-9))
    return np.array([length / 2]) if count <= 1 else np.linspace(side / 2, length - side / 2, count)


def merge_detections(found: list[Detections]) -> Detections:
    """Detections of several views of one frame as one: the same person seen in two views merged by
    weighted NMS (in px: the overlap does not depend on the unit)."""
    found = [f for f in found if len(f.scores)]
    if len(found) <= 1:
        return found[0] if found else Detections(np.zeros((0, 4)), np.zeros((0, 4, 2)), np.zeros(0))
    boxes, points, scores = weighted_nms(
        np.concatenate([f.boxes for f in found]),
        np.concatenate([f.keypoints for f in found]),
        np.concatenate([f.scores for f in found]),
    )
    return Detections(boxes, points, scores)


def decode_detections(raw: np.ndarray, logits: np.ndarray, frame: Roi) -> Detections:
    """The detector's outputs (2254, 12) and (2254, 1) -> its people in px (TensorsToDetectionsCalculator:
    offsets of 224 px units from each anchor's centre, box centre and size then 4 keypoints, scores a
    sigmoid of logits clipped to +-100; kept from MIN_SCORE; then weighted NMS and the letterbox's
    removal, which `frame`, the letterbox ROI, undoes)."""
    scores = sigmoid(np.clip(logits[:, 0].astype(np.float64), -100.0, 100.0))
    keep = scores >= MIN_SCORE
    if not keep.any():
        return Detections(np.zeros((0, 4)), np.zeros((0, 4, 2)), np.zeros(0))
    values, anchors = raw[keep] / DETECTOR_SIZE, ANCHORS[keep]
    centre, size = values[:, 0:2] + anchors, values[:, 2:4]
    boxes = np.concatenate([centre - size / 2, centre + size / 2], axis=1)  # (K, 4) in [0, 1]
    keypoints = values[:, 4:12].reshape(-1, 4, 2) + anchors[:, None, :]  # (K, 4, 2)
    boxes, keypoints, kept_scores = weighted_nms(boxes, keypoints, scores[keep])
    corners = frame.to_frame(boxes.reshape(-1, 2, 2)).reshape(-1, 4)
    return Detections(corners, frame.to_frame(keypoints), kept_scores)


def iou(box: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """(K,) intersection over union of `box` (4,) with each of `boxes` (K, 4), xmin, ymin, xmax, ymax."""
    lo = np.maximum(box[:2], boxes[:, :2])
    hi = np.minimum(box[2:], boxes[:, 2:])
    inter = np.prod(np.clip(hi - lo, 0, None), axis=1)
    area = np.prod(box[2:] - box[:2])
    areas = np.prod(boxes[:, 2:] - boxes[:, :2], axis=1)
    union = area + areas - inter
    return np.where(union > 0, inter / np.where(union > 0, union, 1.0), 0.0)


def weighted_nms(
    boxes: np.ndarray, keypoints: np.ndarray, scores: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """NonMaxSuppressionCalculator's WEIGHTED algorithm: from the best remaining detection, every
    detection overlapping it by more than NMS_IOU (itself included) is merged into one whose box and
    keypoints are their score-weighted means and whose score is the best's."""
    order = np.argsort(-scores, kind="stable")
    boxes, keypoints, scores = boxes[order], keypoints[order], scores[order]
    out_boxes, out_points, out_scores = [], [], []
    remaining = np.arange(len(scores))
    while remaining.size:
        best = remaining[0]
        near = iou(boxes[best], boxes[remaining]) > NMS_IOU
        group = remaining[near]
        w = scores[group][:, None]
        out_boxes.append((boxes[group] * w).sum(axis=0) / w.sum())
        out_points.append((keypoints[group] * w[:, :, None]).sum(axis=0) / w.sum())
        out_scores.append(scores[best])
        remaining = remaining[~near]
    return np.stack(out_boxes), np.stack(out_points), np.array(out_scores)


def alignment_roi(centre: np.ndarray, scale_point: np.ndarray) -> Roi:
    """The ROI of two points in px (AlignmentPointsRectsCalculator then RectTransformationCalculator, as
    pose_detection_to_roi.pbtxt and pose_landmarks_to_roi.pbtxt set them): centred on the first, of
    side twice their distance times ROI_SCALE, turned so that the second is straight above the first
    (rotation_vector_target_angle_degrees 90, DetectionsToRectsCalculator::ComputeRotation)."""
    dx, dy = scale_point - centre
    angle = np.pi / 2 - np.arctan2(-dy, dx)
    angle = angle - 2 * np.pi * np.floor((angle + np.pi) / (2 * np.pi))  # NormalizeRadians
    size = 2.0 * float(np.hypot(dx, dy)) * ROI_SCALE
    return Roi(float(centre[0]), float(centre[1]), size, float(angle))


def crop(image: np.ndarray, roi: Roi, side: int, zero_border: bool) -> np.ndarray:
    """(side, side, 3) float32 in [0, 1]: the ROI of the RGB uint8 `image` (H, W, 3) resampled
    bilinearly, as ImageToTensorConverterOpenCV does it: the ROI's corners onto the tensor's corners,
    cv::warpPerspective with INTER_LINEAR; outside the frame zero (BORDER_ZERO, the detector's) or the
    nearest edge pixel (the landmark model's default, BORDER_REPLICATE)."""
    import cv2  # the `video` extra; the same call as MediaPipe's CPU path, 20 x numpy's speed

    corners = roi.corners().astype(np.float32)  # (4, 2) top-left, top-right, bottom-right, bottom-left
    square = np.array([[0, 0], [side, 0], [side, side], [0, side]], np.float32)
    matrix = cv2.getPerspectiveTransform(corners, square)
    border = cv2.BORDER_CONSTANT if zero_border else cv2.BORDER_REPLICATE
    warped = cv2.warpPerspective(image, matrix, (side, side), flags=cv2.INTER_LINEAR, borderMode=border)
    return np.asarray(np.asarray(warped, dtype=np.float32) / np.float32(255.0))


def sigmoid(x: np.ndarray) -> np.ndarray:
    """The logistic function."""
    return np.asarray(1.0 / (1.0 + np.exp(-x)))


def refine_from_heatmap(points: np.ndarray, heatmap: np.ndarray) -> np.ndarray:
    """(39, 2) landmarks in [0, 1] of the ROI, moved to the confidence-weighted mean cell of their
    heatmap's REFINE_KERNEL window where its best confidence reaches REFINE_MIN_CONFIDENCE
    (RefineLandmarksFromHeatmapCalculator: the window around the landmark's cell, cut at the edges,
    confidence a sigmoid of the heatmap; a landmark outside the heatmap is kept). All landmarks at
    once: each window's cells gathered, those off the heatmap weighing nothing."""
    side = heatmap.shape[0]
    half = (REFINE_KERNEL - 1) // 2
    cells = np.trunc(points * side).astype(np.int64)  # (39, 2) col, row; C++ float -> int: towards zero
    inside = ((cells >= 0) & (cells < side)).all(axis=1)  # (39,)
    step = np.arange(-half, half + 1)
    cols = cells[:, 0, None, None] + step[None, None, :]  # (39, 1, k)
    rows = cells[:, 1, None, None] + step[None, :, None]  # (39, k, 1)
    valid = (cols >= 0) & (cols < side) & (rows >= 0) & (rows < side)  # (39, k, k)
    joint = np.arange(len(points))[:, None, None]
    raw = heatmap[np.clip(rows, 0, side - 1), np.clip(cols, 0, side - 1), joint]  # (39, k, k)
    confidence = sigmoid(raw.astype(np.float64)) * valid
    total = confidence.sum(axis=(1, 2))  # (39,)
    refine = inside & (confidence.max(axis=(1, 2)) >= REFINE_MIN_CONFIDENCE) & (total > 0)
    safe = np.where(total > 0, total, 1.0)
    mean_col = (confidence * cols).sum(axis=(1, 2)) / safe
    mean_row = (confidence * rows).sum(axis=(1, 2)) / safe
    refined = np.stack([mean_col, mean_row], axis=1) / side
    return np.where(refine[:, None], refined, np.asarray(points, dtype=np.float64))


@dataclass(frozen=True)
class Landmarks:
    """One person's landmarks in a frame."""

    points: np.ndarray  # (33, 2) px
    visibility: np.ndarray  # (33,) in [0, 1]
    presence: np.ndarray  # (33,) in [0, 1]
    auxiliary: np.ndarray  # (2, 2) px: the hip centre and the scale point the next ROI is made of
    score: float  # the pose flag: the model's confidence that a person is in the ROI


def decode_landmarks(raw: np.ndarray, flag: float, heatmap: np.ndarray, roi: Roi) -> Landmarks:
    """The landmark model's outputs (195,), its pose flag and heatmap (64, 64, 39) -> the person's
    landmarks in px (TensorsToLandmarksCalculator: 39 rows of x, y, z, visibility, presence in 256 px
    units of the ROI, visibility and presence through a sigmoid; refined from the heatmap; projected
    into the frame through the ROI)."""
    rows = raw.reshape(LANDMARKS, 5).astype(np.float64)
    points = refine_from_heatmap(rows[:, :2] / LANDMARK_SIZE, heatmap)
    frame_points = roi.to_frame(points)
    return Landmarks(
        points=frame_points[:POSE_LANDMARKS],
        visibility=sigmoid(rows[:POSE_LANDMARKS, 3]),
        presence=sigmoid(rows[:POSE_LANDMARKS, 4]),
        auxiliary=frame_points[POSE_LANDMARKS : POSE_LANDMARKS + 2],
        score=float(flag),
    )
