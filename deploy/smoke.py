"""Smoke-check a running service from outside: health, POST /lift, gRPC health, Lift and LiftStream, /metrics.

    python deploy/smoke.py --http http://127.0.0.1:8000 --grpc 127.0.0.1:50051

Exits 0 when every check passes, 1 with the failed check otherwise. Used by deploy/test-container.sh.
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable

import grpc
import httpx
from grpc_health.v1 import health_pb2, health_pb2_grpc

from repnet._proto.repnet.v1 import lifter_pb2, lifter_pb2_grpc

# A standing person facing the camera, Human3.6M 17-joint order, pixels (x right, y down).
STANDING_POSE = [
    [500, 500], [470, 500], [475, 600], [478, 700], [530, 500], [525, 600], [522, 700], [500, 440],
    [500, 380], [500, 360], [500, 330], [540, 385], [560, 440], [570, 495], [460, 385], [440, 440],
    [430, 495],
]  # fmt: skip
FLAT_POSE = [float(v) for point in STANDING_POSE for v in point]


class CheckFailed(Exception):
    """A smoke check did not hold."""


def require(condition: bool, message: str) -> None:
    """Raise CheckFailed with `message` unless `condition` holds."""
    if not condition:
        raise CheckFailed(message)


def check_http(http: httpx.Client) -> None:
    """Health, readiness and a lift over HTTP."""
    require(http.get("/healthz").status_code == 200, "/healthz is not 200")
    require(http.get("/readyz").status_code == 200, "/readyz is not 200")
    reply = http.post("/lift", json={"poses": [{"keypoints": STANDING_POSE}]})
    require(reply.status_code == 200, f"POST /lift: {reply.status_code} {reply.text[:300]}")
    body = reply.json()
    [pose] = body["poses"]
    require(len(body["joints"]) == 17 and bool(body["model_id"]), "reply lacks joints or model_id")
    require(len(pose["pose_3d"]) == 17 and all(len(p) == 3 for p in pose["pose_3d"]), "pose_3d is not 17x3")
    require(all(math.isfinite(v) for p in pose["pose_3d"] for v in p), "pose_3d is not finite")
    require(max(abs(v) for v in pose["pose_3d"][0]) < 1e-3, "pelvis is not at the origin")
    require(len(pose["camera"]) == 2 and len(pose["camera"][0]) == 3, "camera is not 2x3")
    error = pose["reprojection_error_px"]
    print(f"POST /lift ok: model {body['model_id']}, reprojection error {error:.2f} px")
    bad = http.post("/lift", json={"poses": [{"keypoints": STANDING_POSE[:16]}]})
    require(bad.status_code == 422, f"16 joints for h36m17 should be 422, got {bad.status_code}")
    print(f"POST /lift with 16 joints -> 422: {bad.json()['detail'][0]['message']}")


def check_grpc(address: str) -> None:
    """Health, a unary Lift and a LiftStream over gRPC."""
    with grpc.insecure_channel(address) as channel:
        request = health_pb2.HealthCheckRequest(service="")
        health = health_pb2_grpc.HealthStub(channel).Check(request, timeout=5)
        require(health.status == health_pb2.HealthCheckResponse.SERVING, f"gRPC health: {health.status}")
        print("gRPC health: SERVING")
        stub = lifter_pb2_grpc.PoseLifterStub(channel)
        reply = stub.Lift(lifter_pb2.LiftRequest(poses=[lifter_pb2.Pose2D(keypoints=FLAT_POSE)]), timeout=10)
        require(len(reply.poses) == 1 and len(reply.poses[0].pose_3d) == 51, "gRPC Lift: not one 17x3 pose")
        pose = lifter_pb2.Pose2D(keypoints=FLAT_POSE)
        frames = [lifter_pb2.LiftFrame(frame_id=i, pose=pose) for i in range(5)]
        ids = [result.frame_id for result in stub.LiftStream(iter(frames), timeout=10)]
        require(ids == list(range(5)), f"LiftStream answered frames {ids}")
        print("gRPC Lift and LiftStream (5 frames, in order) ok")


def check_metrics(http: httpx.Client) -> None:
    """The request counters of the calls above on /metrics."""
    text = http.get("/metrics").text
    needles = ['repnet_requests_total{method="Lift",outcome="ok",transport="http"}',
               'repnet_requests_total{method="LiftStream",outcome="ok",transport="grpc"}',
               "repnet_request_duration_seconds_bucket", "repnet_model_info{"]  # fmt: skip
    for needle in needles:
        require(needle in text, f"/metrics lacks {needle}")
    print("GET /metrics ok")


def main(argv: list[str] | None = None) -> int:
    """Run every check against a running server; 0 when all pass."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--http", default="http://127.0.0.1:8000", help="base URL of the HTTP API")
    parser.add_argument("--grpc", default="127.0.0.1:50051", help="host:port of the gRPC server")
    args = parser.parse_args(argv)
    with httpx.Client(base_url=args.http, timeout=10) as http:
        checks: list[tuple[str, Callable[[], None]]] = [
            ("http", lambda: check_http(http)), ("grpc", lambda: check_grpc(args.grpc)),
            ("metrics", lambda: check_metrics(http))]  # fmt: skip
        for name, check in checks:
            try:
                check()
            except (CheckFailed, httpx.HTTPError, grpc.RpcError, KeyError, ValueError) as err:
                print(f"smoke check '{name}' FAILED: {err}", file=sys.stderr)
                return 1
    print("all smoke checks passed")
    return 0


if __name__ == "__main__":
    sys.exit(main())
