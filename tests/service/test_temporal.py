"""Temporal lifting on the bundled models: over HTTP (causal and offline clips, their field rules)
and over a gRPC LiftStream (tracks, several people per frame, their limits and errors)."""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import grpc
import numpy as np
import pytest
from fastapi.testclient import TestClient
from prometheus_client import CollectorRegistry

from repnet._proto.repnet.v1 import lifter_pb2, lifter_pb2_grpc
from repnet.runtime.batchers import LiftBatcher
from repnet.runtime.lifter import Lifter
from repnet.runtime.plans import TemporalModels
from repnet.server.app import build_app, build_batcher, build_grpc_server, load_temporal
from repnet.server.config import Settings
from repnet.server.metrics import Metrics
from tests.conftest import POSE_3D, project


def clip(frames: int, noise_px: float, seed: int = 0, turn: float = 0.6) -> np.ndarray:
    """(frames, 17, 2) px of a person turning slowly, with detector noise."""
    rng = np.random.default_rng(seed)
    return np.stack(
        [project(POSE_3D, yaw_deg=10 + turn * f) + rng.normal(0, noise_px, (17, 2)) for f in range(frames)]
    )


def accel(poses: np.ndarray) -> float:
    """Mean acceleration (mm / frame^2) of (n, 17, 3) answers."""
    return float(np.linalg.norm(poses[2:] - 2 * poses[1:-1] + poses[:-2], axis=-1).mean())


@dataclass
class Temporal:
    client: TestClient
    stub: lifter_pb2_grpc.PoseLifterStub
    models: TemporalModels
    metrics: Metrics


def temporal_service(lifter: Lifter, settings: Settings) -> Iterator[Temporal]:
    metrics = Metrics(CollectorRegistry())
    models = load_temporal(settings, lifter, metrics)
    assert models is not None and "causal" in models.engines
    engine: LiftBatcher = build_batcher(lifter, metrics, settings)
    server = build_grpc_server(engine, metrics, settings, models)
    server.start()
    channel = grpc.insecure_channel(f"localhost:{server.port}")
    try:
        with TestClient(build_app(engine, metrics, settings, models), base_url="http://localhost") as client:
            yield Temporal(client, lifter_pb2_grpc.PoseLifterStub(channel), models, metrics)  # type: ignore[no-untyped-call]
    finally:
        channel.close()
        server.stop(0).wait()
        engine.close(10)
        for temporal in models.engines.values():
            temporal.close(10)


@pytest.fixture(scope="module")
def temporal(lifter: Lifter) -> Iterator[Temporal]:
    settings = Settings(grpc_port=0, intra_op_threads=1, stream_max_tracks=3, max_tracks=5, track_idle_s=0.5)
    yield from temporal_service(lifter, settings)


def lift(
    client: TestClient, points: np.ndarray, mode: str, fps: float = 30.0, **extra: Any
) -> list[dict[str, Any]]:
    poses = [{"keypoints": p.tolist(), "track_id": "a", "frame": f} for f, p in enumerate(points)]
    response = client.post("/lift", json={"poses": poses, "temporal": mode, "fps": fps, **extra})
    assert response.status_code == 200, response.json()
    return list(response.json()["poses"])


def camera_poses(replies: list[dict[str, Any]]) -> np.ndarray:
    return np.array([r["pose_3d_camera"] for r in replies])


@pytest.mark.parametrize("mode", ["causal", "offline"])
def test_a_temporal_clip_shakes_less_than_its_frames_lifted_alone(temporal: Temporal, mode: str) -> None:
    points = clip(60, noise_px=4.0)
    alone, smooth = lift(temporal.client, points, "off"), lift(temporal.client, points, mode)
    assert all(r["temporal"] and r["track_id"] == "a" for r in smooth)
    assert not any(r["temporal"] for r in alone)
    assert accel(camera_poses(smooth)) < 0.3 * accel(camera_poses(alone))
    # pose_3d, K and the reprojection stay one answer: pose_3d_camera = pose_3d R^T
    reply = smooth[30]
    turned = np.array(reply["pose_3d"]) @ np.array(reply["rotation"]).T
    np.testing.assert_allclose(turned, reply["pose_3d_camera"], atol=0.05)


def test_a_causal_answer_does_not_change_with_later_frames(temporal: Temporal) -> None:
    points = clip(40, noise_px=3.0)
    before = camera_poses(lift(temporal.client, points, "causal"))
    changed = points.copy()
    changed[21] += 40.0
    after = camera_poses(lift(temporal.client, changed, "causal"))
    np.testing.assert_array_equal(after[:21], before[:21])
    assert np.abs(after[21] - before[21]).max() > 1.0


def test_offline_answers_see_both_sides_and_one_tracks_bones_keep_their_length(temporal: Temporal) -> None:
    points = clip(40, noise_px=3.0)
    changed = points.copy()
    changed[21] += 40.0
    before = camera_poses(lift(temporal.client, points, "offline"))
    after = camera_poses(lift(temporal.client, changed, "offline"))
    assert np.abs(after[15] - before[15]).max() > 1e-3  # frame 21 is in frame 15's window
    parents = [-1, 0, 1, 2, 0, 4, 5, 0, 7, 8, 9, 8, 11, 12, 8, 14, 15]
    bones = np.linalg.norm(before[:, 1:] - before[:, parents[1:]], axis=-1)  # (frames, 16)
    assert bones.std(axis=0).max() < 0.01


def test_tracks_of_one_request_are_independent_and_answers_keep_request_order(temporal: Temporal) -> None:
    a, b = clip(20, 3.0, seed=1), clip(20, 3.0, seed=2, turn=-0.8) + [150.0, 0.0]
    alone = {
        name: camera_poses(lift(temporal.client, points, "causal")) for name, points in (("a", a), ("b", b))
    }
    poses = []
    for f in range(20):  # b before a in each frame, and one untracked pose between
        poses.append({"keypoints": b[f].tolist(), "track_id": "b", "frame": f})
        poses.append({"keypoints": a[f].tolist()})
        poses.append({"keypoints": a[f].tolist(), "track_id": "a", "frame": f})
    body = {"poses": poses, "temporal": "causal", "fps": 30}
    replies = temporal.client.post("/lift", json=body).json()["poses"]
    np.testing.assert_allclose(camera_poses(replies[2::3]), alone["a"], atol=1e-4)
    np.testing.assert_allclose(camera_poses(replies[0::3]), alone["b"], atol=1e-4)
    assert [r["track_id"] for r in replies[:3]] == ["b", None, "a"] and not replies[1]["temporal"]


@pytest.mark.parametrize(
    ("body", "field", "code"),
    [
        ({"temporal": "causal"}, "fps", "fps_missing"),
        ({"temporal": "offline", "fps": 0.0}, "fps", "fps_range"),
        ({"temporal": "causal", "fps": 1000.0}, "fps", "fps_range"),
        ({"temporal": "causal", "fps": 30, "drop_frame": 3}, "poses[3].frame", "frame_missing"),
        ({"temporal": "causal", "fps": 30, "repeat_frame": 4}, "poses[4].frame", "frame_repeated"),
        ({"temporal": "sometimes", "fps": 30}, "temporal", "malformed"),
        ({"temporal": "offline", "fps": 30, "frame_at": (2, 2**63)}, "poses[2].frame", "malformed"),
        ({"temporal": "causal", "fps": 30, "frame_at": (5, 2**53)}, "poses[5].frame", "malformed"),
    ],
)
def test_bad_temporal_fields_get_a_field_level_422(
    temporal: Temporal, body: dict[str, Any], field: str, code: str
) -> None:
    poses = [{"keypoints": p.tolist(), "track_id": "a", "frame": f} for f, p in enumerate(clip(8, 1.0))]
    if (k := body.pop("drop_frame", None)) is not None:
        del poses[k]["frame"]
    if (k := body.pop("repeat_frame", None)) is not None:
        poses[k]["frame"] = poses[k - 1]["frame"]
    if (at := body.pop("frame_at", None)) is not None:
        poses[at[0]]["frame"] = at[1]
    response = temporal.client.post("/lift", json={"poses": poses, **body})
    assert response.status_code == 422
    items = response.json()["detail"]
    assert any(i["field"] == field and i["code"] == code for i in items), items


def test_a_temporal_request_takes_more_poses_than_a_batch_but_not_more_than_its_limit(
    temporal: Temporal,
) -> None:
    points = clip(1, 0.0)[0].tolist()
    limit = temporal.models.max_poses
    poses = [{"keypoints": points, "track_id": "a", "frame": f} for f in range(limit + 1)]
    response = temporal.client.post("/lift", json={"poses": poses, "temporal": "offline", "fps": 50})
    assert response.status_code == 422 and response.json()["detail"][0]["code"] == "batch_too_large"
    assert str(limit) in response.json()["detail"][0]["reason"]


def test_the_largest_frame_number_is_lifted(temporal: Temporal) -> None:
    points = clip(3, 1.0)
    poses = [{"keypoints": p.tolist(), "track_id": "a", "frame": 2**53 - 3 + f} for f, p in enumerate(points)]
    response = temporal.client.post("/lift", json={"poses": poses, "temporal": "offline", "fps": 30})
    assert response.status_code == 200 and all(r["temporal"] for r in response.json()["poses"])


def test_a_tracked_frame_number_past_the_limit_gets_a_frame_error(temporal: Temporal) -> None:
    (message,) = frames(clip(1, 1.0))
    message.frame_id = 2**63
    (result,) = temporal.stub.LiftStream(iter([message]))
    assert result.frame_id == 2**63 and result.error.code == 3
    assert [(v.field, v.code) for v in result.error.violations] == [("frame_id", "frame_range")]


def frames(points: np.ndarray, track: str = "a", fps: float = 30.0) -> list[lifter_pb2.LiftFrame]:
    return [
        lifter_pb2.LiftFrame(
            frame_id=f, track_id=track, fps=fps, pose=lifter_pb2.Pose2D(keypoints=p.ravel().tolist())
        )
        for f, p in enumerate(points)
    ]


def test_a_stream_answers_a_track_as_a_causal_request_does(temporal: Temporal) -> None:
    points = clip(30, 3.0)
    results = list(temporal.stub.LiftStream(iter(frames(points))))
    assert all(r.pose.temporal and r.pose.track_id == "a" for r in results)
    streamed = np.array([np.reshape(r.pose.pose_3d_camera, (17, 3)) for r in results])
    np.testing.assert_allclose(streamed, camera_poses(lift(temporal.client, points, "causal")), atol=1e-3)


def test_several_people_in_one_frame_are_tracked_each_as_alone(temporal: Temporal) -> None:
    a, b = clip(15, 3.0, seed=3), clip(15, 3.0, seed=4, turn=-1.0) + [200.0, 0.0]
    messages = [
        lifter_pb2.LiftFrame(
            frame_id=f,
            fps=30.0,
            people=[
                lifter_pb2.TrackedPose(track_id="b", pose=lifter_pb2.Pose2D(keypoints=b[f].ravel().tolist())),
                lifter_pb2.TrackedPose(track_id="a", pose=lifter_pb2.Pose2D(keypoints=a[f].ravel().tolist())),
            ],
        )
        for f in range(15)
    ]
    results = list(temporal.stub.LiftStream(iter(messages)))
    assert [[p.track_id for p in r.people] for r in results] == [["b", "a"]] * 15
    together = np.array([np.reshape(r.people[1].pose.pose_3d_camera, (17, 3)) for r in results])
    alone = [np.reshape(r.pose.pose_3d_camera, (17, 3)) for r in temporal.stub.LiftStream(iter(frames(a)))]
    np.testing.assert_allclose(together, np.array(alone), atol=1e-3)


def test_stream_track_rules_give_frame_and_person_errors(temporal: Temporal) -> None:
    pose = lifter_pb2.Pose2D(keypoints=clip(1, 0.0)[0].ravel().tolist())
    person = lifter_pb2.TrackedPose
    messages = [
        lifter_pb2.LiftFrame(frame_id=0, track_id="a", pose=pose),  # no fps
        lifter_pb2.LiftFrame(frame_id=1, fps=30, pose=pose, people=[person(track_id="a", pose=pose)]),
        lifter_pb2.LiftFrame(frame_id=2, fps=30, people=[person(track_id="a", pose=pose)] * 2),
        lifter_pb2.LiftFrame(frame_id=3, fps=30, people=[person(track_id="", pose=pose)]),
        lifter_pb2.LiftFrame(frame_id=5, fps=30, track_id="a", pose=pose),
        lifter_pb2.LiftFrame(frame_id=4, fps=30, track_id="a", pose=pose),  # back in time for track a
        lifter_pb2.LiftFrame(frame_id=6, fps=30, people=[person(track_id=t, pose=pose) for t in "bcd"]),
    ]
    results = list(temporal.stub.LiftStream(iter(messages)))
    codes = [[v.code for v in r.error.violations] for r in results[:4]]
    assert codes == [["fps_missing"], ["pose_and_people"], ["track_repeated"], ["track_id"]]
    assert results[4].pose.temporal
    assert results[5].error.violations[0].field == "frame_id" and results[5].error.code == 3
    # a stream holds at most 3 tracks: a, b, c; d is refused, the others answered
    people = results[6].people
    assert [p.WhichOneof("result") for p in people] == ["pose", "pose", "error"]
    assert people[2].error.violations[0].code == "too_many_tracks"
    assert people[2].error.code == grpc.StatusCode.RESOURCE_EXHAUSTED.value[0]  # a quota, not bad input


def test_a_streams_tracks_are_freed_when_it_ends(temporal: Temporal) -> None:
    list(temporal.stub.LiftStream(iter(frames(clip(5, 1.0), track="x"))))
    assert temporal.models.budget.open == 0
    assert temporal.metrics.registry.get_sample_value("repnet_open_tracks") == 0
    assert temporal.metrics.registry.get_sample_value("repnet_track_state_bytes") == 0


def test_the_model_description_lists_the_temporal_models_and_their_limit(temporal: Temporal) -> None:
    described = temporal.client.get("/v1/model").json()
    causal = temporal.models.engines["causal"].lifter
    assert described["limits"]["max_temporal_poses"] == temporal.models.max_poses
    assert described["limits"]["company_wait_ms"] == Settings().company_wait_ms  # the batching window's
    entry = next(e for e in described["temporal"] if e["mode"] == "causal")
    assert entry == {"mode": "causal", "window": causal.contract.window, "grid_fps": causal.contract.grid_fps,
                     "max_fps": causal.contract.max_fps, "model_id": causal.model_id}  # fmt: skip
    assert [e["mode"] for e in described["temporal"]] == sorted(temporal.models.engines)


def test_a_service_without_temporal_models_describes_none(client: TestClient) -> None:
    described = client.get("/v1/model").json()
    assert described["temporal"] == [] and described["limits"]["max_temporal_poses"] is None


def test_a_frame_holds_at_most_a_requests_poses_of_people(temporal: Temporal) -> None:
    pose = lifter_pb2.Pose2D(keypoints=clip(1, 0.0)[0].ravel().tolist())
    people = [lifter_pb2.TrackedPose(track_id=f"p{k}", pose=pose) for k in range(1025)]  # the limit: 1024
    (result,) = temporal.stub.LiftStream(iter([lifter_pb2.LiftFrame(frame_id=0, fps=30, people=people)]))
    assert result.error.code == grpc.StatusCode.INVALID_ARGUMENT.value[0] and not result.people
    assert [(v.field, v.code) for v in result.error.violations] == [("people", "too_many_people")]


def test_a_track_without_frames_is_dropped_while_its_stream_stays_open(temporal: Temporal) -> None:
    """Idle tracks go after track_idle_s (0.5 s here) though the stream sends untracked frames, or
    nothing at all, meanwhile (they stayed until the stream ended before)."""
    pose = lifter_pb2.Pose2D(keypoints=clip(1, 0.0)[0].ravel().tolist())
    open_tracks: list[float | None] = []

    def gauge() -> float | None:
        return temporal.metrics.registry.get_sample_value("repnet_open_tracks")

    def messages() -> Iterator[lifter_pb2.LiftFrame]:
        yield lifter_pb2.LiftFrame(
            frame_id=0, fps=30, people=[lifter_pb2.TrackedPose(track_id="p", pose=pose)]
        )
        yield lifter_pb2.LiftFrame(frame_id=1, fps=30, track_id="q", pose=pose)
        deadline = time.monotonic() + 5
        while gauge() != 2 and time.monotonic() < deadline:
            time.sleep(0.01)
        open_tracks.append(gauge())
        for k in range(6):  # untracked frames only, for 1.2 s
            time.sleep(0.2)
            yield lifter_pb2.LiftFrame(frame_id=2 + k, pose=pose)
        open_tracks.append(gauge())
        yield lifter_pb2.LiftFrame(frame_id=8, fps=30, track_id="r", pose=pose)
        time.sleep(1.2)  # nothing at all
        open_tracks.append(gauge())

    results = list(temporal.stub.LiftStream(messages()))
    assert len(results) == 9 and results[8].pose.temporal
    assert open_tracks == [2, 0, 0]


def test_temporal_answers_carry_the_root_over_http_and_a_stream(temporal: Temporal) -> None:
    """With intrinsics (and a height), a tracked clip's temporal answers place each root as single
    poses do; a stream's frames with the same camera get the same roots as the causal request."""
    points = clip(20, 2.0)
    camera = {"focal_px": [1145.0, 1145.0], "principal_point_px": [512.0, 515.0]}
    http = lift(temporal.client, points, "causal", intrinsics=camera, person_height_m=1.6)
    assert all(r["temporal"] and r["root_height_source"] == "given" for r in http)
    roots = np.array([r["root_camera_m"] for r in http])
    assert (roots[:, 2] > 1.0).all() and np.isfinite(roots).all()
    sent = frames(points)
    for frame in sent:
        frame.pose.intrinsics.CopyFrom(lifter_pb2.CameraIntrinsics(fx=1145.0, fy=1145.0, cx=512.0, cy=515.0))
        frame.pose.person_height_m = 1.6
    streamed = list(temporal.stub.LiftStream(iter(sent)))
    assert all(r.pose.temporal and r.pose.root_height_source == "given" for r in streamed)
    np.testing.assert_allclose([list(r.pose.root_camera_m) for r in streamed], roots, atol=2e-3)
    alone = lift(temporal.client, points, "causal")  # no intrinsics: no root
    assert all(r["root_camera_m"] is None and r["root_height_source"] is None for r in alone)
