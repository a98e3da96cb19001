"""gRPC API on a real server at a free localhost port: Lift, LiftStream, errors, health, reflection."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Iterator

import grpc
import numpy as np
import pytest
from fastapi.testclient import TestClient
from grpc_health.v1 import health_pb2
from grpc_reflection.v1alpha import reflection_pb2
from prometheus_client import CollectorRegistry

from repnet._proto.repnet.v1 import lifter_pb2, lifter_pb2_grpc
from repnet.core.formats import FORMATS, from_model_joints
from repnet.server.grpc.api import SERVICE_NAME
from tests.conftest import POSE_2D, GrpcHandle
from tests.service.invalid_inputs import CASES, Case, good, to_proto_pose, to_proto_request, with_joint

Stub = lifter_pb2_grpc.PoseLifterStub


def lift_error(stub: Stub, request: lifter_pb2.LiftRequest) -> grpc.RpcError:
    with pytest.raises(grpc.RpcError) as info:
        stub.Lift(request, timeout=10)
    return info.value


def test_lift_answers_like_http(stub: Stub, client: TestClient) -> None:
    reply = stub.Lift(to_proto_request({"poses": [good(), with_joint(5, None)]}), timeout=10)
    http = client.post("/lift", json={"poses": [good(), with_joint(5, None)]}).json()
    assert reply.model_id == http["model_id"] and list(reply.joints) == http["joints"]
    assert len(reply.poses) == 2
    for got, want in zip(reply.poses, http["poses"], strict=True):
        np.testing.assert_allclose(np.reshape(got.pose_3d, (17, 3)), want["pose_3d"], rtol=1e-5, atol=1e-3)
        np.testing.assert_allclose(np.reshape(got.reprojection, (17, 2)), want["reprojection"], atol=1e-3)
        np.testing.assert_allclose(np.reshape(got.rotation, (3, 3)), want["rotation"], atol=1e-6)
        np.testing.assert_allclose(np.reshape(got.camera, (2, 3)), want["camera"], rtol=1e-6)
        assert got.scale == pytest.approx(want["scale"], rel=1e-6)
        assert list(got.imputed) == want["imputed"] and list(got.derived) == want["derived"]
    assert reply.poses[1].imputed[5] and not reply.poses[0].imputed[5]


@pytest.mark.parametrize("name", ["coco18", "body25b", "halpe26", "wholebody133"])
def test_lift_takes_every_detector_format_as_http_does(stub: Stub, client: TestClient, name: str) -> None:
    points, present = from_model_joints(FORMATS[name], POSE_2D[None])
    pose = {"keypoints": [p.tolist() if ok else None for p, ok in zip(points[0], present[0], strict=True)]}
    pose["format"] = name
    (got,) = stub.Lift(to_proto_request({"poses": [pose]}), timeout=10).poses
    (want,) = client.post("/lift", json={"poses": [pose]}).json()["poses"]
    np.testing.assert_allclose(np.reshape(got.pose_3d, (17, 3)), want["pose_3d"], rtol=1e-5, atol=1e-3)
    assert list(got.imputed) == want["imputed"] and list(got.derived) == want["derived"]
    assert len(pose["keypoints"]) == len(FORMATS[name].joint_names) != 17


def test_missing_flag_hides_the_joints_coordinates(stub: Stub) -> None:
    base = to_proto_pose(with_joint(5, None))
    nan = lifter_pb2.Pose2D()
    nan.CopyFrom(base)
    nan.keypoints[10], nan.keypoints[11] = float("nan"), float("inf")
    a, b = stub.Lift(lifter_pb2.LiftRequest(poses=[base, nan]), timeout=10).poses
    np.testing.assert_allclose(b.pose_3d, a.pose_3d, rtol=1e-5, atol=1e-3)  # rows of one run
    np.testing.assert_allclose(b.camera, a.camera, rtol=1e-5, atol=1e-9)


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_lift_rejects_with_the_http_message(stub: Stub, client: TestClient, case: Case) -> None:
    error = lift_error(stub, to_proto_request(case.request))
    assert error.code() == grpc.StatusCode.INVALID_ARGUMENT
    http = client.post(
        "/lift", content=json.dumps(case.request), headers={"content-type": "application/json"}
    )
    assert error.details() == "; ".join(item["message"] for item in http.json()["detail"])
    assert case.field in (error.details() or "")


@pytest.mark.parametrize(
    ("pose", "field", "reason"),
    [
        (lifter_pb2.Pose2D(keypoints=[1.0] * 33), "poses[0].keypoints", "2 values (x, y) per joint, got 33"),
        (
            lifter_pb2.Pose2D(keypoints=POSE_2D.ravel().tolist(), missing=[True] * 3),
            "poses[0].missing",
            "no values or one per joint (17), got 3",
        ),
    ],
)
def test_lift_rejects_a_bad_layout(stub: Stub, pose: lifter_pb2.Pose2D, field: str, reason: str) -> None:
    error = lift_error(stub, lifter_pb2.LiftRequest(poses=[pose]))
    assert error.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert (error.details() or "").startswith(f"{field}: expected") and reason in (error.details() or "")


def test_lift_refuses_a_message_over_the_limit(stub: Stub) -> None:
    pose = to_proto_pose(good())
    error = lift_error(stub, lifter_pb2.LiftRequest(poses=[pose] * 800))  # ~115 kB, limit 64 KiB
    assert error.code() == grpc.StatusCode.RESOURCE_EXHAUSTED


def frames(count: int, bad_every: int) -> Iterator[lifter_pb2.LiftFrame]:
    for i in range(count):
        if i % bad_every == bad_every - 1:
            pose = to_proto_pose(with_joint(4, [float("nan"), 1.0]))
        else:
            pose = to_proto_pose(good(keypoints=(POSE_2D + i).tolist()))
        yield lifter_pb2.LiftFrame(frame_id=10_000 + 7 * i, pose=pose)


def test_stream_answers_every_frame_in_order(stub: Stub, registry: CollectorRegistry) -> None:
    count, bad_every = 300, 25
    results = list(stub.LiftStream(frames(count, bad_every), timeout=60))
    assert [r.frame_id for r in results] == [10_000 + 7 * i for i in range(count)]
    for i, result in enumerate(results):
        bad = i % bad_every == bad_every - 1
        assert result.WhichOneof("result") == ("error" if bad else "pose"), i
    # A frame's answer is its own: translating the input moves the reprojection along.
    for i in (0, 1, 137):
        reprojection = np.reshape(results[i].pose.reprojection, (17, 2))
        np.testing.assert_allclose(reprojection.mean(0), (POSE_2D + i).mean(0), atol=1e-2)
    done = registry.get_sample_value
    assert (
        done("repnet_requests_total", {"transport": "grpc", "method": "LiftStream", "outcome": "ok"}) == 288
    )
    assert (
        done("repnet_requests_total", {"transport": "grpc", "method": "LiftStream", "outcome": "invalid"})
        == 12
    )
    assert done("repnet_open_streams") == 0 and done("repnet_in_flight_requests", {"transport": "grpc"}) == 0


def test_stream_error_result_carries_the_http_reason(stub: Stub, client: TestClient) -> None:
    bad = with_joint(4, [float("nan"), 1.0])
    (result,) = stub.LiftStream(iter([lifter_pb2.LiftFrame(frame_id=3, pose=to_proto_pose(bad))]), timeout=10)
    http = client.post("/lift", content=json.dumps(bad), headers={"content-type": "application/json"}).json()
    assert result.frame_id == 3 and result.error.code == grpc.StatusCode.INVALID_ARGUMENT.value[0]
    (violation,) = result.error.violations
    assert (
        violation.field == "pose.keypoints[4]" and violation.joint == 4 and violation.joint_name == "left_hip"
    )
    assert violation.reason == http["detail"][0]["reason"] and violation.code == "non_finite"
    assert result.error.message == f"pose.keypoints[4] (left_hip): {violation.reason}"


def test_empty_frame_gets_an_error_and_the_stream_goes_on(stub: Stub) -> None:
    sent = [lifter_pb2.LiftFrame(frame_id=1), lifter_pb2.LiftFrame(frame_id=2, pose=to_proto_pose(good()))]
    first, second = stub.LiftStream(iter(sent), timeout=10)
    assert first.error.violations[0].code == "joint_count" and second.HasField("pose")


def test_health_reports_serving_then_not_serving(grpc_handle: GrpcHandle) -> None:
    check = grpc_handle.channel.unary_unary(
        "/grpc.health.v1.Health/Check",
        request_serializer=health_pb2.HealthCheckRequest.SerializeToString,
        response_deserializer=health_pb2.HealthCheckResponse.FromString,
    )
    for service in ("", SERVICE_NAME):
        reply = check(health_pb2.HealthCheckRequest(service=service), timeout=5)
        assert reply.status == health_pb2.HealthCheckResponse.SERVING
    grpc_handle.health.enter_graceful_shutdown()  # what SIGTERM does first
    for service in ("", SERVICE_NAME):
        reply = check(health_pb2.HealthCheckRequest(service=service), timeout=5)
        assert reply.status == health_pb2.HealthCheckResponse.NOT_SERVING


def test_reflection_lists_the_services(grpc_handle: GrpcHandle) -> None:
    reflect = grpc_handle.channel.stream_stream(
        "/grpc.reflection.v1alpha.ServerReflection/ServerReflectionInfo",
        request_serializer=reflection_pb2.ServerReflectionRequest.SerializeToString,
        response_deserializer=reflection_pb2.ServerReflectionResponse.FromString,
    )
    (reply,) = reflect(iter([reflection_pb2.ServerReflectionRequest(list_services="")]), timeout=5)
    names = {s.name for s in reply.list_services_response.service}
    assert {"repnet.v1.PoseLifter", "grpc.health.v1.Health"} <= names


def test_a_cancelled_stream_releases_its_frames(stub: Stub, registry: CollectorRegistry) -> None:
    release = threading.Event()

    def endless() -> Iterator[lifter_pb2.LiftFrame]:
        for i in range(3):
            yield lifter_pb2.LiftFrame(frame_id=i, pose=to_proto_pose(good()))
        release.wait(30)  # the client goes quiet, then cancels

    call = stub.LiftStream(endless(), timeout=30)
    assert [next(call).frame_id for _ in range(3)] == [0, 1, 2]
    call.cancel()
    release.set()
    deadline = time.monotonic() + 10
    while registry.get_sample_value("repnet_open_streams") != 0:
        assert time.monotonic() < deadline, "the stream was never closed"
        time.sleep(0.01)
    assert registry.get_sample_value("repnet_in_flight_requests", {"transport": "grpc"}) == 0
    assert stub.Lift(to_proto_request({"poses": [good()]}), timeout=10).poses  # the server goes on


def test_frames_read_together_get_the_answers_they_get_alone(stub: Stub) -> None:
    """Frames that arrive together are prepared as one group: mixed thresholds, formats and invalid
    frames among them must not change any frame's answer."""
    confidence = [1.0] * 17
    confidence[13] = 0.5  # left wrist: visible at threshold 0.2, missing at 0.9
    sent = []
    for i in range(40):
        pose = good(keypoints=(POSE_2D * (1 + 0.01 * i)).tolist(), confidence=confidence)
        frame = lifter_pb2.LiftFrame(frame_id=i, pose=to_proto_pose(pose))
        if i % 3 == 1:
            frame.confidence_threshold = 0.9
        if i % 7 == 6:
            frame.confidence_threshold = 1.5  # out of range: this frame alone is refused
        if i % 11 == 10:
            frame.pose.keypoints[8] = float("inf")
        sent.append(frame)
    streamed = list(stub.LiftStream(iter(sent), timeout=30))
    assert [r.frame_id for r in streamed] == list(range(40))
    for frame, result in zip(sent, streamed, strict=True):
        (alone,) = stub.LiftStream(iter([frame]), timeout=10)
        assert result.WhichOneof("result") == alone.WhichOneof("result"), frame.frame_id
        if result.HasField("error"):
            assert result.error == alone.error
        else:
            assert list(result.pose.visible) == list(alone.pose.visible)
            np.testing.assert_allclose(result.pose.pose_3d, alone.pose.pose_3d, rtol=1e-4, atol=1e-2)
    assert not streamed[1].pose.visible[13] and streamed[0].pose.visible[13]
    assert streamed[6].error.violations[0].field == "confidence_threshold"


def test_undecodable_frame_ends_the_stream_after_the_frames_before_it(grpc_handle: GrpcHandle) -> None:
    raw: grpc.StreamStreamMultiCallable[bytes, bytes] = grpc_handle.channel.stream_stream(
        "/repnet.v1.PoseLifter/LiftStream"
    )  # bytes in, bytes out
    good_frames = [
        lifter_pb2.LiftFrame(frame_id=i, pose=to_proto_pose(good())).SerializeToString() for i in range(3)
    ]
    call = raw(iter([*good_frames, b"\xff\xff\xff\xff\x0f not a protobuf message"]), timeout=10)
    answers = []

    def read_all() -> None:
        for answer in call:
            answers.append(lifter_pb2.LiftFrameResult.FromString(answer))

    with pytest.raises(grpc.RpcError) as raised:
        read_all()
    assert raised.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert "cannot be decoded" in (raised.value.details() or "")
    assert [a.frame_id for a in answers] == [0, 1, 2] and all(a.HasField("pose") for a in answers)


def test_lift_and_stream_carry_the_format_warning(stub: Stub) -> None:
    coco, present = from_model_joints(FORMATS["coco17"], POSE_2D[None].astype(np.float32))
    pose = {"keypoints": [p.tolist() if ok else None for p, ok in zip(coco[0], present[0], strict=True)]}
    reply = stub.Lift(to_proto_request({"poses": [pose, good()]}), timeout=10)
    assert "look like coco17, not h36m17" in reply.poses[0].warnings[0]
    assert list(reply.poses[1].warnings) == []
    frames = [lifter_pb2.LiftFrame(frame_id=i, pose=to_proto_pose(p)) for i, p in enumerate([good(), pose])]
    results = list(stub.LiftStream(iter(frames), timeout=10))
    assert [len(r.pose.warnings) for r in results] == [0, 1]


def _intrinsics(fx: float = 1145.0, cx: float = 512.0) -> lifter_pb2.CameraIntrinsics:
    return lifter_pb2.CameraIntrinsics(fx=fx, fy=fx, cx=cx, cy=515.0)


def test_intrinsics_turn_pose_3d_camera_like_http(stub: Stub, client: TestClient) -> None:
    keypoints = (POSE_2D + [400.0, 0.0]).tolist()  # a person off to the right of the image
    camera = {"focal_px": [1145.0, 1145.0], "principal_point_px": [512.0, 515.0]}
    http = client.post("/lift", json={"keypoints": keypoints, "intrinsics": camera}).json()["poses"][0]
    plain = client.post("/lift", json={"keypoints": keypoints}).json()["poses"][0]
    pose = to_proto_pose({"keypoints": keypoints})
    by_request = stub.Lift(lifter_pb2.LiftRequest(poses=[pose], intrinsics=_intrinsics()), timeout=10).poses[
        0
    ]
    pose.intrinsics.CopyFrom(_intrinsics())
    by_pose = stub.Lift(
        lifter_pb2.LiftRequest(poses=[pose], intrinsics=_intrinsics(cx=0.0)), timeout=10
    ).poses[0]
    for got in (by_request, by_pose):  # the pose's own intrinsics win over the request's
        np.testing.assert_allclose(np.reshape(got.pose_3d_camera, (17, 3)), http["pose_3d_camera"], atol=1e-2)
    assert not np.allclose(http["pose_3d_camera"], plain["pose_3d_camera"], atol=1.0)
    frame = lifter_pb2.LiftFrame(frame_id=1, pose=pose)
    (streamed,) = list(stub.LiftStream(iter([frame]), timeout=10))
    np.testing.assert_allclose(
        np.reshape(streamed.pose.pose_3d_camera, (17, 3)), http["pose_3d_camera"], atol=1e-2
    )


@pytest.mark.parametrize(
    ("where", "camera", "field"),
    [
        ("request", _intrinsics(fx=0.0), "intrinsics.fx"),
        ("request", _intrinsics(cx=float("nan")), "intrinsics.cx"),
        ("pose", _intrinsics(fx=-5.0), "poses[0].intrinsics.fx"),
        ("pose", _intrinsics(cx=float("inf")), "poses[0].intrinsics.cx"),
    ],
)
def test_bad_intrinsics_are_invalid_argument(
    stub: Stub, where: str, camera: lifter_pb2.CameraIntrinsics, field: str
) -> None:
    pose = to_proto_pose(good())
    request = lifter_pb2.LiftRequest(poses=[pose])
    if where == "pose":
        request.poses[0].intrinsics.CopyFrom(camera)
    else:
        request.intrinsics.CopyFrom(camera)
    error = lift_error(stub, request)
    assert error.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert (error.details() or "").startswith(f"{field}: must be finite"), error.details()


def test_image_size_scales_normalised_keypoints_per_pose_or_per_request(stub: Stub) -> None:
    size = lifter_pb2.ImageSize(width=1280.0, height=720.0)
    normalised = (POSE_2D / [1280.0, 720.0]).ravel().tolist()

    def reprojection(pose: lifter_pb2.Pose2D, **fields: lifter_pb2.ImageSize) -> list[float]:
        return list(stub.Lift(lifter_pb2.LiftRequest(poses=[pose], **fields)).poses[0].reprojection)

    pixels = reprojection(lifter_pb2.Pose2D(keypoints=POSE_2D.ravel().tolist()))
    per_pose = reprojection(lifter_pb2.Pose2D(keypoints=normalised, image_size=size))
    per_request = reprojection(lifter_pb2.Pose2D(keypoints=normalised), image_size=size)
    np.testing.assert_allclose([per_pose, per_request], [pixels, pixels], rtol=1e-5, atol=1e-3)
    bad = lifter_pb2.Pose2D(keypoints=normalised, image_size=lifter_pb2.ImageSize(width=0.0, height=720.0))
    err = lift_error(stub, lifter_pb2.LiftRequest(poses=[bad]))
    assert err.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert err.details().startswith("poses[0].image_size.width: must be a finite number of pixels > 0")


def test_root_camera_m_and_the_persons_height_like_http(stub: Stub, client: TestClient) -> None:
    keypoints = (POSE_2D + [400.0, 0.0]).tolist()
    camera = {"focal_px": [1145.0, 1145.0], "principal_point_px": [512.0, 515.0]}
    http = client.post("/lift", json={"keypoints": keypoints, "intrinsics": camera, "person_height_m": 1.8})
    root = http.json()["poses"][0]["root_camera_m"]
    pose = to_proto_pose({"keypoints": keypoints})
    by_request = stub.Lift(
        lifter_pb2.LiftRequest(poses=[pose], intrinsics=_intrinsics(), person_height_m=1.8), timeout=10
    ).poses[0]
    pose.person_height_m = 1.8  # the pose's own height wins over the request's
    by_pose = stub.Lift(
        lifter_pb2.LiftRequest(poses=[pose], intrinsics=_intrinsics(), person_height_m=0.9), timeout=10
    ).poses[0]
    for got in (by_request, by_pose):
        np.testing.assert_allclose(list(got.root_camera_m), root, atol=1e-4)
        assert got.root_height_source == "given"
    plain = stub.Lift(lifter_pb2.LiftRequest(poses=[to_proto_pose({"keypoints": keypoints})]), timeout=10)
    assert not plain.poses[0].root_camera_m and not plain.poses[0].HasField("root_height_source")
