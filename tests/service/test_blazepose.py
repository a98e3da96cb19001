"""BlazePose's numpy steps against known values: anchors, weighted NMS, the ROI of two points, the crop."""

from __future__ import annotations

import numpy as np

from repnet.runtime.blazepose import (
    ANCHORS,
    Roi,
    alignment_roi,
    crop,
    decode_detections,
    letterbox,
    refine_from_heatmap,
    weighted_nms,
)


def test_anchors_are_the_detectors_2254_grid_cells() -> None:
    # 28 x 28 cells of 2 anchors (stride 8), 14 x 14 of 2 (16), 7 x 7 of 6 (three layers of stride 32)
    assert ANCHORS.shape == (28 * 28 * 2 + 14 * 14 * 2 + 7 * 7 * 6, 2) == (2254, 2)
    np.testing.assert_allclose(ANCHORS[0], [0.5 / 28, 0.5 / 28])
    np.testing.assert_allclose(ANCHORS[1], ANCHORS[0])  # two anchors per cell
    np.testing.assert_allclose(ANCHORS[2], [1.5 / 28, 0.5 / 28])  # x runs first
    np.testing.assert_allclose(ANCHORS[-6:], [[6.5 / 7, 6.5 / 7]] * 6)


def test_weighted_nms_merges_overlapping_boxes_by_score_and_keeps_the_best_score() -> None:
    boxes = np.array([[0.0, 0.0, 1.0, 1.0], [0.1, 0.0, 1.1, 1.0], [3.0, 3.0, 4.0, 4.0]])
    points = np.zeros((3, 4, 2))
    points[:, 0] = [[0.0, 0.0], [1.0, 1.0], [5.0, 5.0]]
    out_boxes, out_points, scores = weighted_nms(boxes, points, np.array([0.6, 0.9, 0.7]))
    assert scores.tolist() == [0.9, 0.7]
    np.testing.assert_allclose(out_boxes[0], [0.06, 0.0, 1.06, 1.0])  # (0.6 * 0 + 0.9 * 0.1) / 1.5
    np.testing.assert_allclose(out_points[0, 0], [0.6, 0.6])
    np.testing.assert_allclose(out_boxes[1], boxes[2])


def test_the_roi_of_a_person_standing_upright_is_not_turned() -> None:
    roi = alignment_roi(np.array([100.0, 200.0]), np.array([100.0, 120.0]))  # scale point above the hips
    assert (roi.x, roi.y) == (100.0, 200.0) and roi.size == 2 * 80 * 1.25
    assert abs(roi.rotation) < 1e-12
    lying = alignment_roi(np.array([100.0, 200.0]), np.array([180.0, 200.0]))  # head to the right
    np.testing.assert_allclose(lying.rotation, np.pi / 2)
    # the ROI's top (y = 0 of the crop) is towards the head
    np.testing.assert_allclose(lying.to_frame(np.array([0.5, 0.0])), [100.0 + lying.size / 2, 200.0])


def test_crop_samples_the_roi_and_pads_outside_the_frame() -> None:
    image = np.zeros((40, 60, 3), np.uint8)
    image[10:20, 30:40] = 255
    tensor = crop(image, Roi(35.0, 15.0, 10.0, 0.0), 10, zero_border=True)
    assert tensor.shape == (10, 10, 3) and tensor.min() == 1.0  # exactly the white square
    frame = letterbox(60, 40)  # the detector's view: the frame in a 60 x 60 square
    padded = crop(image, frame, 60, zero_border=True)
    # the frame sits 10 rows down the square; its white square too
    assert padded[:10].max() == 0.0 and padded[20:30, 30:40].min() == 1.0 and padded[30:50].max() == 0.0
    replicate = crop(np.full((40, 60, 3), 128, np.uint8), frame, 60, zero_border=False)
    np.testing.assert_allclose(replicate, 128 / 255, rtol=1e-6)


def test_refinement_moves_a_landmark_to_its_heatmaps_peak_only_when_confident() -> None:
    heatmap = np.full((64, 64, 2), -10.0, np.float32)
    heatmap[33, 31, 0] = 10.0  # row 33, column 31
    points = np.array([[32.5 / 64, 32.5 / 64], [10.5 / 64, 10.5 / 64]])
    out = refine_from_heatmap(points, heatmap)
    np.testing.assert_allclose(out[0], [31 / 64, 33 / 64], atol=1e-4)
    np.testing.assert_allclose(out[1], points[1])  # no confident cell near it: kept


def test_no_detection_below_the_score_threshold() -> None:
    raw = np.zeros((2254, 12), np.float32)
    found = decode_detections(raw, np.full((2254, 1), -5.0, np.float32), letterbox(640, 480))
    assert found.boxes.shape == (0, 4) and found.scores.shape == (0,)
