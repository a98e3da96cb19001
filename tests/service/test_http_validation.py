"""Every HTTP input rule: a 4xx whose JSON body names the field (pose and joint) and the reason."""

from __future__ import annotations

import json
from collections.abc import Iterator
from typing import Any

import pytest
from fastapi.testclient import TestClient

from repnet.core.errors import SPLIT_HINT
from tests.conftest import POSE_2D
from tests.service.detector_files import FIXTURES
from tests.service.invalid_inputs import CASES, Case, good


def post_raw(client: TestClient, body: str | bytes) -> Any:
    return client.post("/lift", content=body, headers={"content-type": "application/json"})


def only_item(response: Any, status: int = 422) -> dict[str, Any]:
    assert response.status_code == status, response.text
    detail = response.json()["detail"]
    assert isinstance(detail, list) and len(detail) == 1, detail
    item: dict[str, Any] = detail[0]
    assert item["message"].endswith(item["reason"]) and item["message"].startswith(item["field"])
    return item


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_lift_rejects_input_naming_field_and_reason(client: TestClient, case: Case) -> None:
    item = only_item(post_raw(client, json.dumps(case.request)))  # NaN / Infinity as JSON literals
    assert item["field"] == case.field
    assert item["code"] == case.code
    assert case.reason in item["reason"]
    assert (item["pose"], item["joint"], item["joint_name"]) == (case.pose, case.joint, case.joint_name)


def test_lift_reports_every_broken_joint(client: TestClient) -> None:
    keypoints: list[Any] = POSE_2D.tolist()
    keypoints[2], keypoints[11] = [float("nan"), 0.0], [0.0, float("-inf")]
    response = post_raw(client, json.dumps({"poses": [good(), good(keypoints=keypoints)]}))
    assert response.status_code == 422
    fields = [(d["field"], d["joint_name"]) for d in response.json()["detail"]]
    assert fields == [("poses[1].keypoints[2]", "right_knee"), ("poses[1].keypoints[11]", "left_shoulder")]


@pytest.mark.parametrize("value", ['"12"', '"abc"', "true", "[1]", "{}"])
def test_lift_rejects_non_numbers(client: TestClient, value: str) -> None:
    keypoints = [json.dumps(p) for p in POSE_2D.tolist()]
    keypoints[6] = f"[{value}, 2.0]"
    item = only_item(post_raw(client, '{"poses": [{"keypoints": [' + ", ".join(keypoints) + "]}]}"))
    assert item["field"] == "poses[0].keypoints[6][0]"
    assert (item["pose"], item["joint"]) == (0, 6)
    assert "valid number" in item["reason"]


def test_lift_rejects_rows_of_mixed_lengths_with_one_item(client: TestClient) -> None:
    keypoints: list[Any] = POSE_2D.tolist()
    keypoints[3] = [1.0, 2.0, 3.0]
    item = only_item(client.post("/lift", json={"keypoints": keypoints}))
    assert item["field"] == "poses[0].keypoints" and "got rows of 2 and 3 values" in item["reason"]


@pytest.mark.parametrize(
    ("keypoints", "reason"),
    [
        ([[*p, 0.9, 0.0, 1.0] for p in POSE_2D.tolist()], "got rows of 5 values"),
        ([[p[0]] for p in POSE_2D.tolist()], "got rows of 1 values"),
        ([v for p in POSE_2D.tolist() for v in p], "got a flat list of 34 numbers"),
        ([POSE_2D.tolist(), POSE_2D.tolist()], "got a list of 2 poses"),
    ],
    ids=["rows_of_5", "rows_of_1", "flat", "list_of_poses"],
)
def test_lift_rejects_a_wrongly_shaped_array_with_one_item(
    client: TestClient, keypoints: list[Any], reason: str
) -> None:
    """One item for the whole array, not one per joint (17 near-identical errors before)."""
    item = only_item(client.post("/lift", json={"keypoints": keypoints}))
    assert item["field"] == "poses[0].keypoints" and reason in item["reason"], item
    assert "[x, y, confidence]" in item["reason"] or '{"poses": [{"keypoints": ...}' in item["reason"]


def test_lift_rejects_a_confidence_given_twice(client: TestClient) -> None:
    keypoints = [[*p, 0.9] for p in POSE_2D.tolist()]
    item = only_item(client.post("/lift", json={"keypoints": keypoints, "confidence": [0.9] * 17}))
    assert (item["field"], item["code"]) == ("poses[0].confidence", "confidence_twice")


def test_lift_asks_for_the_image_size_of_mediapipe_landmarks(client: TestClient) -> None:
    landmarks = [[0.5, 0.5, -0.1, 0.99]] * 33
    item = only_item(client.post("/lift", json={"keypoints": landmarks, "format": "mediapipe33"}))
    assert (item["field"], item["code"]) == ("poses[0].image_size", "image_size_needed")
    assert "image_size [width, height]" in item["reason"]


def test_lift_names_the_format_of_mediapipe_rows(client: TestClient) -> None:
    landmarks = [[0.5, 0.5, -0.1, 0.99]] * 17
    item = only_item(client.post("/lift", json={"keypoints": landmarks, "image_size": [640, 480]}))
    assert (item["field"], item["code"]) == ("poses[0].keypoints", "layout_format")
    assert "send format mediapipe33" in item["reason"]


def test_lift_rejects_unknown_fields(client: TestClient) -> None:
    item = only_item(client.post("/lift", json={"poses": [good(keypoint=[])]}))
    assert item["field"] == "poses[0].keypoint" and "not permitted" in item["reason"]


def test_lift_rejects_invalid_json(client: TestClient) -> None:
    item = only_item(post_raw(client, '{"keypoints": [[1, 2],'))
    assert item["field"] == "body" and "JSON" in item["reason"]


def test_lift_rejects_a_body_over_the_limit(client: TestClient) -> None:
    body = json.dumps({"poses": [good()] * 200})  # ~90 kB, limit 64 KiB
    item = only_item(post_raw(client, body), status=413)
    assert item["field"] == "body" and "the limit is 65536" in item["reason"]
    assert item["reason"].endswith(f"; {SPLIT_HINT}") and "LiftClient.lift_batch" in item["message"]


def test_lift_rejects_a_streamed_body_over_the_limit(client: TestClient) -> None:
    def chunks() -> Iterator[bytes]:  # no Content-Length: the limit applies while reading
        yield b'{"poses": ['
        for _ in range(200):
            yield json.dumps(good()).encode() + b","
        yield b"]}"

    item = only_item(
        client.post("/lift", content=chunks(), headers={"content-type": "application/json"}), status=413
    )
    assert item["code"] == "body_too_large"


@pytest.mark.parametrize("body", [
    b"", b"null", b"[]", b'"pose"', b"{}", b'{"poses": null}', b'{"poses": [null]}', b'{"keypoints": 5}',
    b'{"keypoints": [[1e400, 1]]}', b'{"keypoints": [[' + b"9" * 400 + b", 1]]}", b"\xff\xfe\x00",
    b"[" * 5000 + b"]" * 5000, b'{"poses": [{"keypoints": []}]}', b'{"keypoints": [null, null]}',
    b'{"poses": [{"keypoints": ' + json.dumps(POSE_2D.tolist()).encode() + b', "format": 7}]}',
])  # fmt: skip
def test_lift_never_answers_5xx(client: TestClient, body: bytes) -> None:
    response = post_raw(client, body)
    assert 400 <= response.status_code < 500, response.text
    assert response.json()["detail"]


@pytest.mark.parametrize(
    ("headers", "got"),
    [
        ({}, "got no content-type"),
        ({"content-type": "text/plain"}, "got content-type: text/plain"),
        ({"content-type": "application/x-www-form-urlencoded"}, "curl -d sends a form"),
    ],
    ids=["none", "text", "form"],
)
def test_a_body_that_is_not_sent_as_json_is_told_so(
    client: TestClient, headers: dict[str, str], got: str
) -> None:
    """Not "Input should be a valid dictionary": the content-type is what is wrong."""
    body = json.dumps({"keypoints": POSE_2D.tolist()})
    item = only_item(client.post("/lift", content=body, headers=headers))
    assert (item["field"], item["code"]) == ("body", "content_type")
    assert "expected a JSON body with content-type: application/json" in item["reason"]
    assert got in item["reason"]


def test_raw_openpose_output_is_told_how_to_send_it(client: TestClient) -> None:
    person = {"person_id": [-1], "pose_keypoints_2d": [0.0] * 75}
    item = only_item(client.post("/lift", json={"version": 1.3, "people": [person]}))
    assert (item["field"], item["code"]) == ("body", "detector_output")
    assert "this is OpenPose output" in item["reason"] and "repnet lift" in item["reason"]
    assert "pose_keypoints_2d" in item["reason"] and '"body25"' in item["reason"]


@pytest.mark.parametrize(("values", "named"), [(54, '"coco18"'), (75, '"body25" or "body25b"')])
def test_raw_openpose_output_is_told_the_format_of_its_joint_count(
    client: TestClient, values: int, named: str
) -> None:
    person = {"person_id": [-1], "pose_keypoints_2d": [0.0] * values}
    item = only_item(client.post("/lift", json={"version": 1.3, "people": [person]}))
    assert (item["code"], item["reason"].endswith(f"with format {named}")) == ("detector_output", True)


@pytest.mark.parametrize(
    ("name", "said"),
    [("mmpose_video.json", "MMPose inferencer file"), ("yolo_summary.json", "Ultralytics YOLO results"),
     ("mediapipe_python.json", "MediaPipe PoseLandmarker"), ("alphapose-results.json", "AlphaPose results"),
     ("coco_wholebody.json", "COCO-WholeBody")],
)  # fmt: skip
def test_a_detectors_file_posted_whole_is_a_422_saying_what_it_is(
    client: TestClient, name: str, said: str
) -> None:
    """Not "Input should be a valid dictionary": what the body looks like, and what to do."""
    body = json.loads((FIXTURES / name).read_text())
    item = only_item(client.post("/lift", json=body))
    assert (item["field"], item["code"]) == ("body", "detector_output")
    assert (
        said in item["reason"]
        and "repnet lift FILE" in item["reason"]
        and "valid dictionary" not in item["reason"]
    )


def test_raw_coco_results_are_told_how_to_send_them(client: TestClient) -> None:
    results = [{"image_id": 1, "category_id": 1, "keypoints": [1.0, 2.0, 0.9] * 17, "score": 0.9}]
    for body in (results, {"images": [], "annotations": results}):
        item = only_item(client.post("/lift", json=body))
        assert item["code"] == "detector_output" and '"coco17"' in item["reason"], item


def test_zero_joints_of_pairs_are_missing_with_a_warning(client: TestClient) -> None:
    keypoints = POSE_2D.tolist()
    keypoints[3] = [0.0, 0.0]
    zero = client.post("/lift", json={"keypoints": keypoints}).json()["poses"][0]
    keypoints[3] = None
    null = client.post("/lift", json={"keypoints": keypoints}).json()["poses"][0]
    assert zero["pose_3d"] == null["pose_3d"] and not zero["visible"][3]
    assert len(zero["warnings"]) == 1 and "1 joint at exactly (0, 0)" in zero["warnings"][0]
    assert null["warnings"] == []
