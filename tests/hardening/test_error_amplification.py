"""Error amplification: however many values of a request are wrong, the reply lists at most 20
errors plus their count, is built in milliseconds per KB of request, and never stalls /healthz."""

from __future__ import annotations

import json
import math
import threading
import time

import grpc
import httpx

from bench.server import ServiceProcess
from repnet._proto.repnet.v1 import lifter_pb2, lifter_pb2_grpc
from tests.conftest import POSE_2D, LiveService

MAX_ERROR_ITEMS = 20  # repnet.core.errors.MAX_ERROR_ITEMS, the figure the issue asks for

# The probe: a flat list of 300,000 numbers (600 KB) got 300,000 error items, 63 MB, 15.6 s.
FLAT_NUMBERS = 300_000
# "No reply may take more than a few ms per KB of request": the bound, loose for a busy 2-core CI.
MS_PER_KB = 3.0
# Plus a floor for the round trip itself, which a loaded machine (training beside the tests) can
# stretch to 100 ms; the amplification this guards against took seconds (15.6 s for 600 KB).
FLOOR_MS = 500.0


def post(service: ServiceProcess, body: bytes) -> tuple[httpx.Response, float]:
    start = time.perf_counter()
    response = httpx.post(
        f"{service.url}/lift", content=body, headers={"content-type": "application/json"}, timeout=120
    )
    return response, time.perf_counter() - start


def check_bounded(response: httpx.Response, seconds: float, request_bytes: int) -> dict[str, object]:
    assert response.status_code == 422, response.text[:300]
    assert len(response.content) < 16 * 1024, len(response.content)
    assert seconds * 1000 < FLOOR_MS + MS_PER_KB * request_bytes / 1024, seconds
    body = response.json()
    assert isinstance(body, dict)
    assert len(body["detail"]) <= MAX_ERROR_ITEMS
    return body


def test_a_flat_list_of_numbers_is_one_error_and_health_answers_meanwhile(
    service_process: ServiceProcess,
) -> None:
    body = json.dumps({"poses": [{"keypoints": [1] * FLAT_NUMBERS}]}).encode()
    health: list[float] = []
    done = threading.Event()

    def probe() -> None:
        while not done.is_set():
            start = time.perf_counter()
            assert httpx.get(f"{service_process.url}/healthz", timeout=30).status_code == 200
            health.append(time.perf_counter() - start)
            time.sleep(0.02)

    prober = threading.Thread(target=probe)
    prober.start()
    try:
        response, seconds = post(service_process, body)
    finally:
        done.set()
        prober.join()
    found = check_bounded(response, seconds, len(body))
    (item,) = found["detail"]  # type: ignore[misc]
    assert found["error_count"] == 1
    assert item["field"] == "poses[0].keypoints"
    assert f"flat list of {FLAT_NUMBERS} numbers" in item["reason"], item
    assert max(health) < 1.0, health


def test_every_joint_of_every_pose_wrong_lists_20_errors_and_counts_them(
    service_process: ServiceProcess,
) -> None:
    poses = 16  # the fixture's max_request_poses
    keypoints = [[float("nan"), 1.0]] * len(POSE_2D)
    body = json.dumps({"poses": [{"keypoints": keypoints}] * poses}).encode()  # NaN: JSON's extension
    response, seconds = post(service_process, body)
    found = check_bounded(response, seconds, len(body))
    assert len(found["detail"]) == MAX_ERROR_ITEMS  # type: ignore[arg-type]
    assert found["error_count"] == poses * len(POSE_2D)
    first = found["detail"][0]  # type: ignore[index]
    assert first["field"] == "poses[0].keypoints[0]" and first["code"] == "non_finite", first


def test_many_wrong_items_of_any_list_or_object_give_one_item_s_errors(
    service_process: ServiceProcess,
) -> None:
    pose = {"keypoints": POSE_2D.tolist()}
    cases = {
        "poses": {"poses": [1] * 200_000},
        "confidence": {"poses": [{**pose, "confidence": ["high"] * 200_000}]},
        "pairs": {"poses": [{"keypoints": [["x", "y"]] * 100_000}]},
        "empty poses": {"poses": [{}] * 200_000},
        "unknown keys": {"poses": [{**pose, **{f"k{i}": 0 for i in range(100_000)}}]},
    }
    for name, request in cases.items():
        body = json.dumps(request).encode()
        response, seconds = post(service_process, body)
        found = check_bounded(response, seconds, len(body))
        # The first wrong item only (a pair may have both its values wrong), not one per item.
        assert found["error_count"] in (1, 2), (name, found)
    assert httpx.get(f"{service_process.url}/readyz", timeout=5).status_code == 200


def test_a_stream_frame_of_many_bad_people_is_answered_in_fewer_bytes_than_it_sent(
    live_service: LiveService,
) -> None:
    """Issue 30: 1,024 people with NaN poses in a 154 KB frame came back as a 2.9 MB reply (19x)."""
    nan_pose = lifter_pb2.Pose2D(keypoints=[math.nan] * 34)
    people = [lifter_pb2.TrackedPose(track_id=f"p{i}", pose=nan_pose) for i in range(1024)]
    frame = lifter_pb2.LiftFrame(frame_id=1, fps=30, people=people)
    with grpc.insecure_channel(live_service.grpc_target) as channel:
        (result,) = lifter_pb2_grpc.PoseLifterStub(channel).LiftStream(iter([frame]), timeout=60)
    sent, answered = frame.ByteSize(), result.ByteSize()
    assert len(result.people) == 1024 and all(p.WhichOneof("result") == "error" for p in result.people)
    assert answered < sent, (answered, sent)
    assert sum(len(p.error.violations) for p in result.people) == MAX_ERROR_ITEMS  # 20 in all
    first, last = result.people[0].error, result.people[-1].error
    assert first.violations and first.code == last.code == grpc.StatusCode.INVALID_ARGUMENT.value[0]
    assert last.message and len(last.message) <= 80 and not last.violations  # brief, still an error
