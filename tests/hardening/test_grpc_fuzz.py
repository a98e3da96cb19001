"""gRPC LiftStream fuzzing: bad frames get per-frame errors, the stream survives, valid frames are right."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass

import grpc
import numpy as np
import pytest
from prometheus_client import CollectorRegistry

from repnet._proto.repnet.v1 import lifter_pb2, lifter_pb2_grpc
from repnet.core.formats import FORMATS, from_model_joints
from repnet.core.inputs import PoseInput
from repnet.core.keypoints import prepare_poses
from repnet.runtime.batchers import LiftBatcher
from repnet.runtime.lifter import Lifter
from repnet.server.app import build_grpc_server, limits_of
from repnet.server.config import Settings
from repnet.server.metrics import Metrics
from tests.conftest import POSE_2D, GrpcHandle

INVALID_ARGUMENT = grpc.StatusCode.INVALID_ARGUMENT.value[0]
FRAMES = 3000
Pose = lifter_pb2.Pose2D
BAD_CONF = (np.nan, -1.0, 7.0)


@dataclass
class Sent:
    frame: lifter_pb2.LiftFrame
    kind: str
    valid: bool | None  # None: random garbage that may or may not be valid


def _jittered(rng: np.random.Generator) -> np.ndarray:
    """A plausible h36m17 pose (17, 2): the test pose moved, scaled and shaken a little."""
    return (POSE_2D - 512) * rng.uniform(0.5, 2.0) + rng.uniform(100, 900, 2) + rng.normal(0, 3, (17, 2))


def _valid(rng: np.random.Generator) -> tuple[str, Pose]:
    points = _jittered(rng)
    choice = rng.integers(4)
    if choice == 0:
        return "valid", Pose(keypoints=points.ravel().tolist())
    if choice == 1:
        missing = rng.random(17) < 0.3
        missing[:6] = False  # enough joints stay visible
        garbage = np.where(missing[:, None], rng.choice([np.nan, np.inf, 1e30]), points)
        return "valid_missing", Pose(keypoints=garbage.ravel().tolist(), missing=missing.tolist())
    if choice == 2:
        return "valid_confidence", Pose(keypoints=points.ravel().tolist(), confidence=rng.random(17).tolist())
    name = str(rng.choice(["coco17", "mpii16", "body25", "mediapipe33"]))
    source, visible = from_model_joints(FORMATS[name], points[None].astype(np.float32))
    flat = np.where(visible[0][:, None], source[0], 0.0)
    return f"valid_{name}", Pose(keypoints=flat.ravel().tolist(), missing=(~visible[0]).tolist(), format=name)


def _poison(points: np.ndarray, rng: np.random.Generator, value: float) -> list[float]:
    flat = points.ravel().copy()
    flat[rng.integers(flat.size)] = value
    return [float(v) for v in flat]


def _invalid(rng: np.random.Generator) -> tuple[str, Pose | None, float | None]:
    """A frame that breaks one input rule: (kind, pose or None for an empty frame, threshold)."""
    points = _jittered(rng)
    flat = points.ravel().tolist()
    kinds: dict[str, Callable[[], Pose | None]] = {
        "empty_frame": lambda: None,
        "no_values": lambda: Pose(),
        "odd_values": lambda: Pose(keypoints=flat[: 2 * int(rng.integers(1, 17)) + 1]),
        "wrong_joint_count": lambda: Pose(
            keypoints=rng.uniform(0, 900, int(rng.choice([2, 32, 36, 80]))).tolist()
        ),
        "nan": lambda: Pose(keypoints=_poison(points, rng, np.nan)),
        "infinite": lambda: Pose(keypoints=_poison(points, rng, -np.inf)),
        "huge": lambda: Pose(keypoints=_poison(points, rng, float(rng.choice([1e7, -3e38, 1e30])))),
        "unknown_format": lambda: Pose(keypoints=flat, format=str(rng.choice(["coco", "é", "x" * 300]))),
        "confidence_count": lambda: Pose(keypoints=flat, confidence=[0.9] * int(rng.integers(1, 16))),
        "confidence_range": lambda: Pose(
            keypoints=flat, confidence=[0.9] * 16 + [float(rng.choice(BAD_CONF))]
        ),
        "missing_count": lambda: Pose(keypoints=flat, missing=[False] * 3),
        "all_missing": lambda: Pose(keypoints=flat, missing=[True] * 17),
        "one_point": lambda: Pose(keypoints=[321.0, 123.0] * 17),
        "bad_threshold": lambda: Pose(keypoints=flat),
    }
    kind = str(rng.choice(list(kinds)))
    threshold = float(rng.choice([np.nan, -0.5, 1.5])) if kind == "bad_threshold" else None
    return kind, kinds[kind](), threshold


def _garbage(rng: np.random.Generator) -> Pose:
    """Random float32 bit patterns (NaN, inf, denormals included) in a random count."""
    count = int(rng.choice([34, int(rng.integers(0, 200))]))
    values = rng.integers(0, 2**32, count, dtype=np.uint64).astype(np.uint32).view(np.float32)
    return Pose(
        keypoints=values.tolist(), missing=(rng.random(count // 2) < 0.5).tolist() if count % 2 == 0 else []
    )


def make_frames(count: int, seed: int = 0) -> list[Sent]:
    rng = np.random.default_rng(seed)
    sent = []
    for i in range(count):
        frame_id = int(rng.integers(0, 2**64, dtype=np.uint64)) if i % 7 == 0 else i
        roll = rng.random()
        if roll < 0.4:
            kind, pose = _valid(rng)
            sent.append(Sent(lifter_pb2.LiftFrame(frame_id=frame_id, pose=pose), kind, True))
        elif roll < 0.9:
            kind, maybe_pose, threshold = _invalid(rng)
            frame = lifter_pb2.LiftFrame(frame_id=frame_id, confidence_threshold=threshold)
            if maybe_pose is not None:
                frame.pose.CopyFrom(maybe_pose)
            sent.append(Sent(frame, kind, False))
        else:
            sent.append(Sent(lifter_pb2.LiftFrame(frame_id=frame_id, pose=_garbage(rng)), "garbage", None))
    return sent


def expected_poses(lifter: Lifter, frames: list[lifter_pb2.LiftFrame]) -> np.ndarray:
    """(n, 17, 3) pose_3d of valid frames, lifted directly (no gRPC, no batching engine)."""
    inputs = [
        PoseInput(
            np.reshape(f.pose.keypoints, (-1, 2)).astype(np.float64),
            ~np.array(f.pose.missing, bool) if f.pose.missing else np.ones(len(f.pose.keypoints) // 2, bool),
            np.array(f.pose.confidence) if f.pose.confidence else None,
            f.pose.format or "h36m17",
        )
        for f in frames
    ]
    model_input = prepare_poses(inputs, limits_of(Settings())).check()
    return lifter.lift(model_input.keypoints_2d, model_input.visible).pose_3d


@pytest.fixture
def roomy_stub(
    engine_factory: Callable[..., LiftBatcher], lifter: Lifter, metrics: Metrics, settings: Settings
) -> Iterator[lifter_pb2_grpc.PoseLifterStub]:
    """A server whose queue holds a whole stream window, as the defaults do: no frame is refused."""
    engine = engine_factory(lifter, max_batch=64, queue_size=1024)
    server = build_grpc_server(
        engine, metrics, settings.model_copy(update={"grpc_workers": 4, "stream_window_poses": 256})
    )
    server.start()
    with grpc.insecure_channel(f"localhost:{server.port}") as channel:
        yield lifter_pb2_grpc.PoseLifterStub(channel)  # type: ignore[no-untyped-call]
    server.stop(0).wait()


def test_long_stream_of_malformed_frames_answers_each_and_survives(
    roomy_stub: lifter_pb2_grpc.PoseLifterStub, lifter: Lifter, registry: CollectorRegistry
) -> None:
    stub = roomy_stub
    sent = make_frames(FRAMES)

    def requests() -> Iterator[lifter_pb2.LiftFrame]:
        yield from (s.frame for s in sent)

    results = list(stub.LiftStream(requests(), timeout=120))
    assert [r.frame_id for r in results] == [s.frame.frame_id for s in sent]  # all answered, in order
    valid_frames, valid_results = [], []
    for s, result in zip(sent, results, strict=True):
        outcome = result.WhichOneof("result")
        if s.valid is False:
            assert outcome == "error", s.kind
        if s.valid is True:
            assert outcome == "pose", (s.kind, result.error.message)
            valid_frames.append(s.frame)
            valid_results.append(np.reshape(result.pose.pose_3d, (17, 3)))
        if outcome == "error":  # garbage and invalid frames: a client error naming the field
            assert result.error.code == INVALID_ARGUMENT, (s.kind, result.error)
            assert result.error.violations and result.error.message, s.kind
            assert all(v.field.startswith(("pose", "confidence_threshold")) for v in result.error.violations)
    assert len(valid_results) > FRAMES // 3 and {s.kind for s in sent if s.valid is False} >= {
        "empty_frame",
        "nan",
        "huge",
        "wrong_joint_count",
        "odd_values",
        "bad_threshold",
    }
    expected = expected_poses(lifter, valid_frames)
    np.testing.assert_allclose(np.stack(valid_results), expected, rtol=1e-4, atol=0.05)
    value = registry.get_sample_value
    assert (
        value("repnet_open_streams") == 0 and value("repnet_in_flight_requests", {"transport": "grpc"}) == 0
    )
    errors = {"transport": "grpc", "method": "LiftStream", "outcome": "error"}
    assert not value("repnet_requests_total", errors)


def test_undecodable_bytes_end_only_that_stream(grpc_handle: GrpcHandle) -> None:
    raw: grpc.StreamStreamMultiCallable[bytes, bytes] = grpc_handle.channel.stream_stream(
        "/repnet.v1.PoseLifter/LiftStream"
    )  # bytes in, bytes out
    good = lifter_pb2.LiftFrame(frame_id=1, pose=Pose(keypoints=POSE_2D.ravel().tolist()))
    garbage = [good.SerializeToString(), b"\xff\xff\xff\xff\x0f not a protobuf message"]
    with pytest.raises(grpc.RpcError) as refused:  # an undecodable frame is never accepted
        list(raw(iter(garbage), timeout=10))
    assert refused.value.code() in (grpc.StatusCode.INTERNAL, grpc.StatusCode.INVALID_ARGUMENT), refused.value
    frames = [
        lifter_pb2.LiftFrame(frame_id=i, pose=Pose(keypoints=(POSE_2D + i).ravel().tolist()))
        for i in range(5)
    ]
    assert [r.WhichOneof("result") for r in grpc_handle.stub.LiftStream(iter(frames), timeout=10)] == [
        "pose"
    ] * 5
