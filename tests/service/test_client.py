"""Tests for the Python clients against a live service (HTTP and gRPC) and a scripted transport."""

from __future__ import annotations

import asyncio
import json
import re
import socket
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from repnet.client.http import AsyncLiftClient, LiftClient, LiftClientError, LiftResult
from repnet.client.stream import Frame, Person, StreamClient
from repnet.core.formats import FORMATS, MODEL_JOINTS, from_model_joints
from repnet.runtime.lifter import Lifter
from tests.conftest import POSE_2D, SMALL_TEMPORAL_POSES, TEMPORAL_MODES, LiveService, reply_of
from tests.service.test_temporal import clip


def _poses(n: int) -> np.ndarray:
    shifts = np.arange(n, dtype=np.float64)[:, None, None] * [7.0, -3.0]
    return POSE_2D[None] + shifts  # (n, 17, 2)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _assert_matches_lifter(result: LiftResult, lifter: Lifter, points: np.ndarray) -> None:
    expected = reply_of(lifter, points[None]).columns
    np.testing.assert_allclose(result.pose_3d, expected["pose_3d"][0], rtol=1e-4, atol=1e-2)
    np.testing.assert_allclose(result.camera, expected["camera"][0], rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(result.reprojection, expected["reprojection"][0], rtol=1e-4, atol=1e-2)
    np.testing.assert_allclose(result.rotation, expected["rotation"][0], atol=1e-5)
    assert result.scale == pytest.approx(float(expected["scale"][0]), rel=1e-5)


def test_http_lift_returns_typed_result_matching_the_model(live_service: LiveService, lifter: Lifter) -> None:
    with LiftClient(live_service.http_url) as client:
        result = client.lift(POSE_2D)
    assert result.joints == MODEL_JOINTS and result.model_id == lifter.info.model_id
    assert result.pose_3d.shape == (17, 3) and result.pose_3d.dtype == np.float32
    assert result.camera.shape == (2, 3) and result.reprojection.shape == (17, 2)
    assert result.visible.all() and not result.imputed.any() and not result.derived.any()
    _assert_matches_lifter(result, lifter, POSE_2D)


def test_http_batch_is_split_into_requests_and_kept_in_order(
    live_service: LiveService, lifter: Lifter
) -> None:
    poses = _poses(7)
    with LiftClient(live_service.http_url, batch_size=3) as client:
        results = client.lift_batch(poses)
    assert len(results) == 7
    for result, pose in zip(results, poses, strict=True):
        _assert_matches_lifter(result, lifter, pose)


def test_http_coco_pose_with_missing_joint_reports_flags(live_service: LiveService) -> None:
    points, visible = from_model_joints(FORMATS["coco17"], POSE_2D[None])
    points[0, FORMATS["coco17"].joint_names.index("left_wrist")] = np.nan  # the detector missed it
    confidence = np.where(visible[0], 0.9, 0.0)
    confidence[FORMATS["coco17"].joint_names.index("right_knee")] = 0.1  # below the default 0.2
    with LiftClient(live_service.http_url) as client:
        result = client.lift(points[0], format="coco17", confidence=confidence)
    imputed = {MODEL_JOINTS[j] for j in np.flatnonzero(result.imputed)}
    assert imputed == {"spine", "head", "left_wrist", "right_knee"}
    assert {MODEL_JOINTS[j] for j in np.flatnonzero(result.derived)} == {"pelvis", "thorax"}
    np.testing.assert_array_equal(result.visible, ~result.imputed)


def test_http_rejection_carries_the_server_message(live_service: LiveService) -> None:
    bad = POSE_2D.copy()
    with LiftClient(live_service.http_url) as client, pytest.raises(LiftClientError) as info:
        client.lift(bad[:16])  # 16 joints in the h36m17 format
    assert info.value.status == 422
    assert "h36m17 has 17 joints, got 16" in info.value.message
    assert info.value.details[0]["field"] == "poses[0].keypoints"


def test_http_model_and_ready(live_service: LiveService) -> None:
    with LiftClient(live_service.http_url) as client:
        assert client.ready()
        model = client.model()
    assert {f["name"] for f in model["formats"]} == set(FORMATS)


def test_async_client_lifts_batches_concurrently(live_service: LiveService, lifter: Lifter) -> None:
    async def run() -> list[LiftResult]:
        async with AsyncLiftClient(live_service.http_url, batch_size=2) as client:
            return await client.lift_batch(_poses(5))

    results = asyncio.run(run())
    for result, pose in zip(results, _poses(5), strict=True):
        _assert_matches_lifter(result, lifter, pose)


def test_unreachable_server_raises_after_retries() -> None:
    with LiftClient(f"http://127.0.0.1:{_free_port()}", retries=1, backoff=0.01) as client:
        with pytest.raises(LiftClientError, match="cannot reach") as info:
            client.lift(POSE_2D)
        assert info.value.status is None
        assert not client.ready()


def _scripted(statuses: list[int], seen: list[int]) -> httpx.MockTransport:
    """A transport answering with `statuses` in turn (then 200 with a real-looking body)."""
    pose = {"pose_3d": [[0.0] * 3] * 17, "pose_3d_camera": [[0.0] * 3] * 17,
            "camera": [[1.0, 0, 0], [0, 1, 0]], "scale": 1.0, "rotation": np.eye(3).tolist(),
            "reprojection": POSE_2D.tolist(), "reprojection_error_px": 0.5, "visible": [True] * 17,
            "imputed": [False] * 17, "derived": [False] * 17}  # fmt: skip

    def handle(request: httpx.Request) -> httpx.Response:
        seen.append(len(json.loads(request.content)["poses"]))
        status = statuses.pop(0) if statuses else 200
        if status == 503:
            return httpx.Response(503, json={"detail": "the batch queue is full; retry later"})
        return httpx.Response(200, json={"model_id": "m", "joints": list(MODEL_JOINTS), "poses": [pose]})

    return httpx.MockTransport(handle)


def test_503_is_retried_with_backoff() -> None:
    seen: list[int] = []
    with LiftClient("http://test", retries=2, backoff=0.001, transport=_scripted([503, 503], seen)) as client:
        result = client.lift(POSE_2D)
    assert len(seen) == 3 and result.model_id == "m" and result.reprojection_error_px == 0.5


def test_503_gives_up_after_the_last_retry() -> None:
    seen: list[int] = []
    with LiftClient("http://test", retries=1, backoff=0.001, transport=_scripted([503] * 5, seen)) as client:
        with pytest.raises(LiftClientError, match="queue is full") as info:
            client.lift(POSE_2D)
    assert info.value.status == 503 and len(seen) == 2


def test_keypoints_of_the_wrong_rank_are_refused_before_sending() -> None:
    with (
        LiftClient("http://test", transport=_scripted([], [])) as client,
        pytest.raises(
            LiftClientError, match=r"expected keypoints of shape \(N, J, 2\) or \(N, J, 3\).*got \(17, 2\)"
        ),
    ):
        client.lift_batch(POSE_2D)  # (17, 2) is one pose, not a batch
    with (
        LiftClient("http://test", transport=_scripted([], [])) as client,
        pytest.raises(LiftClientError) as info,
    ):
        client.lift(np.zeros((33, 4)))  # MediaPipe rows need the image size
    assert info.value.status == 422 and "multiply x, y by the image size" in info.value.message


def test_stream_answers_every_frame_in_order(live_service: LiveService, lifter: Lifter) -> None:
    poses = _poses(20)
    with StreamClient(live_service.grpc_target, timeout=30) as client:
        results = list(client.stream(Frame(p, frame_id=100 + i) for i, p in enumerate(poses)))
    assert [r.frame_id for r in results] == list(range(100, 120))
    for r, pose in zip(results, poses, strict=True):
        assert r.error is None and r.result is not None
        _assert_matches_lifter(r.result, lifter, pose)


def test_stream_bad_frame_gets_an_error_and_the_stream_goes_on(live_service: LiveService) -> None:
    frames: list[np.ndarray | Frame] = [POSE_2D, Frame(POSE_2D, format="coco99"), POSE_2D]
    with StreamClient(live_service.grpc_target, timeout=30) as client:
        results = list(client.stream(frames))
    assert [r.frame_id for r in results] == [0, 1, 2]
    assert results[0].result is not None and results[2].result is not None
    error = results[1].error
    assert results[1].result is None and error is not None
    assert error.status == "INVALID_ARGUMENT" and "unknown format 'coco99'" in error.message
    assert error.details[0]["field"] == "pose.format"


def test_grpc_unary_lift_matches_http(live_service: LiveService) -> None:
    points = POSE_2D.copy()
    points[13] = np.nan  # left wrist missing
    with StreamClient(live_service.grpc_target, timeout=30) as grpc_client:
        (via_grpc,) = grpc_client.lift_batch(points[None])
    with LiftClient(live_service.http_url) as http_client:
        via_http = http_client.lift(points)
    assert via_grpc.imputed[13] and via_http.imputed[13]
    np.testing.assert_allclose(via_grpc.pose_3d, via_http.pose_3d, rtol=1e-5, atol=1e-3)
    np.testing.assert_allclose(via_grpc.reprojection, via_http.reprojection, rtol=1e-5, atol=1e-3)


def test_grpc_rejection_raises_with_status(live_service: LiveService) -> None:
    with StreamClient(live_service.grpc_target, timeout=30) as client, pytest.raises(LiftClientError) as info:
        client.lift_batch(np.full((1, 17, 2), 5.0))  # every joint at one point
    assert info.value.status == "INVALID_ARGUMENT" and "one point" in info.value.message


def test_stream_can_be_left_early(live_service: LiveService) -> None:
    def endless() -> Iterator[np.ndarray]:
        while True:
            yield POSE_2D

    with StreamClient(live_service.grpc_target, timeout=30) as client:
        results = client.stream(endless())
        first = [next(results) for _ in range(3)]
        results.close()  # cancels the call; the endless request iterator is no longer read
    assert [r.frame_id for r in first] == [0, 1, 2]
    assert all(r.result is not None for r in first)


def test_api_doc_client_snippet_runs_as_written(
    live_service: LiveService, capsys: pytest.CaptureFixture[str]
) -> None:
    """docs/API.md's Python client example, run as it stands (only the addresses point at the test
    server)."""
    readme = (Path(__file__).resolve().parents[2] / "docs" / "API.md").read_text()
    section = readme[readme.index("## Python clients") :]
    snippet = section[section.index("```python\n") + len("```python\n") : section.index("\n```\n")]
    snippet = snippet.replace("http://localhost:8000", live_service.http_url)
    snippet = snippet.replace('"localhost:50051"', repr(live_service.grpc_target))
    exec(compile(snippet, "docs/API.md", "exec"), {"__name__": "api_doc"})
    out = capsys.readouterr().out
    assert out.startswith("(17, 3) [")  # the lift: pose_3d shape, imputed flags, error, warnings
    frames = re.findall(r"^(\d+) \[([^\]]*)\]$", out, re.MULTILINE)  # then one line per stream frame
    assert [int(f) for f, _ in frames] == list(range(10))
    wrists = [np.array(values.split(), float) for _, values in frames]
    assert all(np.linalg.norm(w) > 100 for w in wrists)  # mm from the pelvis: not joint 0


# ---- temporal: tracked poses, clips cut into requests, streams of tracked people ----

PARENTS = [-1, 0, 1, 2, 0, 4, 5, 0, 7, 8, 9, 8, 11, 12, 8, 14, 15]


def two_people(frames: int = 260) -> tuple[np.ndarray, list[str | None], np.ndarray]:
    """A long track "a" with gaps (one too long to bridge), a short track "b" and an untracked pose:
    (N, 17, 2) px, each pose's track and frame number."""
    a, b = clip(frames, 3.0, seed=5), clip(40, 3.0, seed=6, turn=-0.8) + [180.0, 0.0]
    kept = np.ones(frames, bool)
    kept[[30, 31, 32, 100, 101, 102, 103]] = False  # bridged gaps
    kept[150:175] = False  # a gap of 25 frames at 30 fps: the track starts again
    frames_a = np.flatnonzero(kept)
    points = np.concatenate([a[kept], b, POSE_2D[None]])
    tracks = ["a"] * len(frames_a) + ["b"] * len(b) + [None]
    return points, tracks, np.concatenate([frames_a, np.arange(len(b)), [0]])


def bones(poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(n, 16, 3) unit bone directions and (n, 16) lengths of (n, 17, 3) poses."""
    vectors = poses[:, 1:] - poses[:, PARENTS[1:]]
    lengths = np.linalg.norm(vectors, axis=-1)
    return vectors / lengths[..., None], lengths


@pytest.mark.parametrize("mode", TEMPORAL_MODES)
def test_a_clip_longer_than_a_request_is_answered_as_one_request(
    live_service: LiveService, small_service: LiveService, mode: str
) -> None:
    points, tracks, frames = two_people()
    args = {"temporal": mode, "fps": 30.0, "track_ids": tracks, "frames": frames}
    sizes: dict[str, list[int]] = {"one": [], "cut": []}
    with LiftClient(live_service.http_url) as client:
        one = client.lift_batch(points, **args, progress=sizes["one"].append)
    with LiftClient(small_service.http_url) as client:
        assert client.model()["limits"]["max_temporal_poses"] == SMALL_TEMPORAL_POSES
        cut = client.lift_batch(points, **args, progress=sizes["cut"].append)
    assert sizes["one"] == [len(points)] and len(sizes["cut"]) >= 3 and sum(sizes["cut"]) == len(points)
    assert [r.track_id for r in cut] == tracks and [r.temporal for r in cut] == [
        t is not None for t in tracks
    ]
    a, b = (
        np.array([r.pose_3d_camera for r, t in zip(rs, tracks, strict=True) if t == "a"]) for rs in (one, cut)
    )
    # Every window the model read is the one of the single request: each bone points the same way.
    np.testing.assert_allclose(bones(b)[0], bones(a)[0], atol=2e-4)
    # A cut track's bone lengths are the mean over its part, not over the whole track (chunks.py).
    np.testing.assert_allclose(bones(b)[1], bones(a)[1], atol=1.5)
    np.testing.assert_allclose(b, a, atol=3.0)
    for r1, r2, track in zip(one, cut, tracks, strict=True):
        if track != "a":  # a track that fits in a request is sent whole: the same answer
            np.testing.assert_allclose(r2.pose_3d_camera, r1.pose_3d_camera, atol=1e-3)
            np.testing.assert_allclose(r2.pose_3d, r1.pose_3d, atol=1e-3)


def test_cutting_without_context_would_change_the_answers(small_service: LiveService) -> None:
    """The check above can fail: the same parts sent without their context frames read other windows."""
    points, tracks, frames = two_people()
    args = {"temporal": "causal", "fps": 30.0}
    with LiftClient(small_service.http_url) as client:
        whole = client.lift_batch(points[:100], track_ids=tracks[:100], frames=frames[:100], **args)
        alone = client.lift_batch(points[60:100], track_ids=tracks[60:100], frames=frames[60:100], **args)
    directions = [bones(np.array([r.pose_3d_camera for r in rs]))[0] for rs in (whole[60:100], alone)]
    assert np.abs(directions[0] - directions[1]).max() > 0.01


def test_temporal_errors_name_the_callers_pose_and_misuse_is_refused(
    small_service: LiveService, live_service: LiveService
) -> None:
    points, tracks, frames = two_people()
    points[230] = 100.0  # every joint at one point, in the third request
    with LiftClient(small_service.http_url) as client, pytest.raises(LiftClientError) as info:
        client.lift_batch(points, temporal="causal", fps=30.0, track_ids=tracks, frames=frames)
    assert info.value.status == 422 and "poses[230].keypoints" in info.value.message
    assert info.value.details[0]["pose"] == 230
    with LiftClient(live_service.http_url) as client:
        with pytest.raises(ValueError, match="needs fps, track_ids and frames"):
            client.lift_batch(points[:3], temporal="causal", track_ids=["a"] * 3, frames=[0, 1, 2])
        with pytest.raises(ValueError, match="expected 3 track_ids"):
            client.lift_batch(points[:3], temporal="off", track_ids=["a"] * 2)
        with pytest.raises(LiftClientError) as info:  # the service's own rule: fps in (0, 240]
            client.lift_batch(points[:3], temporal="causal", fps=500.0, track_ids=["a"] * 3, frames=[0, 1, 2])
        assert info.value.status == 422 and info.value.details[0]["code"] == "fps_range"


def test_a_mode_the_service_has_no_model_for_is_a_422_before_sending() -> None:
    model = {"limits": {"max_temporal_poses": 100, "max_body_bytes": 1 << 20}, "temporal": []}
    seen: list[str] = []

    def handle(request: httpx.Request) -> httpx.Response:
        seen.append(request.url.path)
        return httpx.Response(200, json=model)

    with LiftClient("http://test", transport=httpx.MockTransport(handle)) as client:
        with pytest.raises(LiftClientError) as info:
            client.lift_batch(_poses(3), temporal="offline", fps=25.0, track_ids=["a"] * 3, frames=[0, 1, 2])
    assert info.value.status == 422 and info.value.details[0]["code"] == "no_temporal_model"
    assert seen == ["/v1/model"]  # no /lift was sent


def test_async_client_cuts_a_clip_as_the_sync_one(small_service: LiveService) -> None:
    points, tracks, frames = two_people(180)
    args = {"temporal": "causal", "fps": 30.0, "track_ids": tracks, "frames": frames}

    async def run() -> list[LiftResult]:
        async with AsyncLiftClient(small_service.http_url, max_concurrency=2) as client:
            return await client.lift_batch(points, **args)

    with LiftClient(small_service.http_url) as client:
        expected = client.lift_batch(points, **args)
    for got, want in zip(asyncio.run(run()), expected, strict=True):
        np.testing.assert_allclose(got.pose_3d_camera, want.pose_3d_camera, atol=1e-3)
        assert got.track_id == want.track_id


def test_stream_client_sends_tracks_and_people_and_reads_their_results(
    live_service: LiveService,
) -> None:
    a, b = clip(12, 2.0, seed=7), clip(12, 2.0, seed=8) + [200.0, 0.0]
    with StreamClient(live_service.grpc_target, timeout=30) as client:
        alone = list(client.stream((Frame(p, track_id="a") for p in a), fps=30.0))
        crowd = list(
            client.stream(
                [
                    Frame(people=[Person("b", b[f]), Person("a", a[f])], frame_id=f, fps=30.0)
                    for f in range(12)
                ]
            )
        )
        with LiftClient(live_service.http_url) as http:
            causal = http.lift_batch(
                a, temporal="causal", fps=30.0, track_ids=["a"] * 12, frames=np.arange(12)
            )
    assert all(r.result is not None and r.result.temporal and r.result.track_id == "a" for r in alone)
    assert [[p.track_id for p in r.people] for r in crowd] == [["b", "a"]] * 12
    for one, many, http_result in zip(alone, crowd, causal, strict=True):
        assert one.result is not None and many.people[1].result is not None
        np.testing.assert_allclose(many.people[1].result.pose_3d_camera, one.result.pose_3d_camera, atol=1e-2)
        np.testing.assert_allclose(one.result.pose_3d_camera, http_result.pose_3d_camera, atol=1e-2)


def test_stream_client_reports_person_errors_and_raises_for_a_frame_it_cannot_send(
    live_service: LiveService,
) -> None:
    with StreamClient(live_service.grpc_target, timeout=30) as client:
        results = client.stream(
            [
                Frame(POSE_2D, track_id="a"),  # no fps: the frame's error
                Frame(people=[Person("a", POSE_2D), Person("a", POSE_2D)], fps=30.0),  # a track twice
                Frame(np.zeros((17, 5))),  # the wrong shape: cannot be sent
            ]
        )
        first, second = next(results), next(results)
        with pytest.raises(LiftClientError, match=r"frame 2 cannot be sent: expected keypoints of shape"):
            next(results)
    assert first.error is not None and first.error.details[0]["code"] == "fps_missing"
    assert second.error is not None and second.error.details[0]["code"] == "track_repeated"


def test_api_doc_sequence_snippet_runs_as_written(
    live_service: LiveService, capsys: pytest.CaptureFixture[str]
) -> None:
    """docs/API.md's Python example of temporal lifting, run as it stands (addresses: the test server)."""
    readme = (Path(__file__).resolve().parents[2] / "docs" / "API.md").read_text()
    section = readme[readme.index("### Sequences: tracks and temporal lifting") :]
    snippet = section[
        section.index("```python\n") + len("```python\n") : section.index(
            "\n```\n", section.index("```python")
        )
    ]
    snippet = snippet.replace("http://localhost:8000", live_service.http_url)
    snippet = snippet.replace('"localhost:50051"', repr(live_service.grpc_target))
    exec(compile(snippet, "docs/API.md", "exec"), {"__name__": "api_doc"})
    lines = capsys.readouterr().out.splitlines()
    assert lines == ["True a", "0 True", "1 True", "2 True", *["[('a', True), ('b', True)]"] * 3]


def test_x_y_confidence_arrays_are_sent_as_keypoints_and_confidence_by_every_client(
    live_service: LiveService,
) -> None:
    body, found = from_model_joints(FORMATS["body25"], POSE_2D[None])
    conf = np.where(found[0], np.linspace(0.9, 0.5, 25), 0.0)
    rows = np.concatenate([body[0], conf[:, None]], axis=1)  # (25, 3) [x, y, c], NaN rows: not found
    with LiftClient(live_service.http_url) as client:
        want = client.lift(body[0], format="body25", confidence=conf)
        got = client.lift(rows, format="body25")
        with pytest.raises(LiftClientError, match="either as the third value of each joint or as"):
            client.lift(rows, format="body25", confidence=conf)
    with StreamClient(live_service.grpc_target, timeout=30) as stream:
        (frame,) = stream.stream([Frame(rows, format="body25")])
        (person,) = stream.stream([Frame(people=[Person("a", rows, format="body25")], fps=30.0)])
    assert frame.result is not None and person.people[0].result is not None
    for result in (got, frame.result):
        np.testing.assert_allclose(result.pose_3d, want.pose_3d, rtol=1e-5, atol=1e-3)
        np.testing.assert_array_equal(result.visible, want.visible)


def test_lift_results_carry_the_root_sync_and_async(live_service: LiveService) -> None:
    camera = (1145.0, 1145.0, 512.0, 515.0)
    with LiftClient(live_service.http_url) as client:
        given = client.lift(POSE_2D, intrinsics=camera, person_height_m=1.7)
        template = client.lift(POSE_2D, intrinsics=camera)
        plain = client.lift(POSE_2D)
    assert given.root_camera_m is not None and given.root_camera_m.shape == (3,)
    assert (given.root_height_source, template.root_height_source) == ("given", "template")
    assert plain.root_camera_m is None and plain.root_height_source is None
    assert (
        template.root_camera_m is not None and abs(template.root_camera_m[2] - given.root_camera_m[2]) > 0.01
    )

    async def lift_async() -> LiftResult:
        async with AsyncLiftClient(live_service.http_url) as client:
            return await client.lift(POSE_2D, intrinsics=camera, person_height_m=1.7)

    np.testing.assert_allclose(asyncio.run(lift_async()).root_camera_m, given.root_camera_m)


def test_stream_client_sends_the_camera_and_height_for_the_root(live_service: LiveService) -> None:
    camera = (1145.0, 1145.0, 512.0, 515.0)
    with LiftClient(live_service.http_url) as client:
        expected = client.lift(POSE_2D, intrinsics=camera, person_height_m=1.7).root_camera_m
    with StreamClient(live_service.grpc_target, timeout=30) as grpc_client:
        (unary,) = grpc_client.lift_batch(POSE_2D[None], intrinsics=camera, person_height_m=1.7)
        (streamed,) = list(grpc_client.stream([POSE_2D], intrinsics=camera, person_height_m=1.7))
    assert (
        streamed.result is not None
        and unary.root_height_source == streamed.result.root_height_source == "given"
    )
    for got in (unary.root_camera_m, streamed.result.root_camera_m):
        np.testing.assert_allclose(got, expected, atol=1e-4)


def test_lift_each_lifts_the_valid_poses_and_gives_the_others_their_error(live_service: LiveService) -> None:
    points = np.stack([POSE_2D, POSE_2D + 30.0, POSE_2D, POSE_2D - 20.0])
    points[1, 3:] = np.nan  # 3 of 17 joints: not lifted
    points[3, 0] = np.inf  # a non-finite coordinate
    with LiftClient(live_service.http_url, batch_size=2) as client:
        each = client.lift_each(points)
        alone = client.lift_batch(points[[0, 2]])
        with pytest.raises(LiftClientError) as refused:  # lift_batch refuses the whole batch
            client.lift_batch(points)
    assert [type(r).__name__ for r in each] == [
        "LiftResult",
        "LiftClientError",
        "LiftResult",
        "LiftClientError",
    ]
    ok = [r for r in each if isinstance(r, LiftResult)]
    np.testing.assert_allclose(ok[0].pose_3d, alone[0].pose_3d, atol=1e-2)  # batches of 1 and 2
    np.testing.assert_allclose(ok[1].pose_3d, alone[1].pose_3d, atol=1e-2)
    error = each[3]
    assert isinstance(error, LiftClientError) and error.status == 422
    assert error.details[0]["pose"] == 3 and error.details[0]["field"].startswith("poses[3].keypoints[0]")
    assert "poses[1]" in refused.value.message


def test_async_lift_each_answers_as_the_sync_client(live_service: LiveService) -> None:
    points = np.stack([POSE_2D, POSE_2D])
    points[0, 2:] = np.nan

    async def run() -> list[Any]:
        async with AsyncLiftClient(live_service.http_url) as client:
            return await client.lift_each(points)

    got = asyncio.run(run())
    assert isinstance(got[0], LiftClientError) and got[0].details[0]["pose"] == 0
    assert isinstance(got[1], LiftResult)
