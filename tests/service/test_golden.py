"""Fixed answers to a fixed set of inputs: every transport's reply (HTTP lifts of each format, temporal
requests with gaps, gRPC Lift and a tracked LiftStream) equals the one stored in golden_answers.json.gz.

The file was written before the package moved into `repnet` (and is written again only when an
answer is meant to change, saying why in the commit): `python -m tests.service.test_golden --write`.
Strings and flags must match exactly; numbers within TOLERANCE, or within RELATIVE of their size
where one float32 step is larger than that (a coordinate past 1,024 mm moves by 1.2e-4 at the least).
The temporal models run their strided convolutions as matrix products since 2026-12-05
(runtime.rewrite): their answers moved by at most one float32 step (1.2e-4 mm), the single-frame
answers, cameras and scores not at all.
"""

from __future__ import annotations

import argparse
import gzip
import json
import math
import queue
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from google.protobuf.json_format import MessageToDict

from repnet._proto.repnet.v1 import lifter_pb2
from repnet.core.formats import FORMATS, from_model_joints
from repnet.server.config import Settings
from tests.conftest import POSE_3D, load_model, project
from tests.service.test_temporal import Temporal, temporal_service

GOLDEN = Path(__file__).with_name("golden_answers.json.gz")
TOLERANCE = 1e-4  # absolute, on every number of every answer (mm, px, ...): issue 35's bound
RELATIVE = 2.0**-22  # two float32 steps of the stored value
# The camera and the scores: within 1e-6 (issue 35), and no relative slack.
STRICT = {"camera": 1e-6, "rotation": 1e-6, "scale": 1e-6, "plausibility": 1e-6, "root_camera_m": 1e-6}


def walk(frames: int, seed: int, noise_px: float = 3.0, shift: float = 0.0) -> np.ndarray:
    """(frames, 17, 2) px of a person turning, with detector noise."""
    rng = np.random.default_rng(seed)
    return np.stack(
        [
            project(POSE_3D, yaw_deg=-40 + 2.5 * f) + [shift, 0] + rng.normal(0, noise_px, (17, 2))
            for f in range(frames)
        ]
    )


def rows(points: np.ndarray, missing: tuple[int, ...] = ()) -> list[Any]:
    return [
        None if j in missing else [round(float(x), 3), round(float(y), 3)] for j, (x, y) in enumerate(points)
    ]


def requests() -> Iterator[tuple[str, dict[str, Any]]]:
    """(name, POST /lift body) of every HTTP case."""
    poses = walk(12, seed=1, noise_px=6.0)
    single = [{"keypoints": rows(p, (3, 16) if k % 5 == 2 else ())} for k, p in enumerate(poses)]
    single[4]["intrinsics"] = {"focal_px": [1145.0, 1145.0], "principal_point_px": [512.0, 515.0]}
    single[5] |= {
        "intrinsics": {"focal_px": [1145.0, 1145.0], "principal_point_px": [512.0, 515.0]},
        "person_height_m": 1.6,
    }
    yield "h36m17", {"poses": single}
    for name in ("coco17", "body25", "mediapipe33", "mpii16"):
        points, visible = from_model_joints(FORMATS[name], poses[:6])
        if name == "mediapipe33":
            body = [
                {"keypoints": [[x / 1000, y / 1000, 0.0, 0.9] if v else [0.0, 0.0, 0.0, 0.0]
                               for (x, y), v in zip(p.tolist(), m, strict=True)]}
                for p, m in zip(points, visible, strict=True)
            ]  # fmt: skip
            yield name, {"format": name, "image_size": [1000, 1000], "poses": body}
            continue
        body = [{"keypoints": [[x, y] if v else None for (x, y), v in zip(p.tolist(), m, strict=True)]}
                for p, m in zip(points, visible, strict=True)]  # fmt: skip
        yield name, {"format": name, "poses": body}
    a, b = walk(40, seed=2), walk(40, seed=3, shift=220.0)
    for mode in ("causal", "offline"):
        tracked = []
        for f in range(40):
            if f % 9 != 4:  # a bridged gap every 9 frames
                tracked.append({"keypoints": rows(a[f]), "track_id": "a", "frame": f})
            if f < 15 or f > 30:  # a gap too long to bridge at 30 fps
                tracked.append({"keypoints": rows(b[f]), "track_id": "b", "frame": 100 + f})
        tracked.append({"keypoints": rows(a[0])})  # untracked
        yield f"temporal-{mode}", {"temporal": mode, "fps": 30, "poses": tracked}


def stream_frames() -> list[lifter_pb2.LiftFrame]:
    a, b = walk(30, seed=4), walk(30, seed=5, shift=-200.0)
    frames = []
    for f in range(30):
        people = [
            lifter_pb2.TrackedPose(track_id="a", pose=lifter_pb2.Pose2D(keypoints=a[f].ravel().tolist()))
        ]
        if f % 7 != 3:
            people.append(
                lifter_pb2.TrackedPose(track_id="b", pose=lifter_pb2.Pose2D(keypoints=b[f].ravel().tolist()))
            )
        frames.append(lifter_pb2.LiftFrame(frame_id=f, fps=30.0, people=people))
    return frames


def lock_step(service: Temporal) -> list[Any]:
    """The stream's answers, each frame sent once the one before is answered: every run holds the
    same poses whatever the machine's speed (a batch's size can change the last bits)."""
    answered = queue.Queue[None]()

    def frames() -> Iterator[lifter_pb2.LiftFrame]:
        for k, frame in enumerate(stream_frames()):
            if k:
                answered.get(timeout=30)
            yield frame

    found = []
    for result in service.stub.LiftStream(frames()):
        found.append(MessageToDict(result))
        answered.put(None)
    return found


def answers(service: Temporal) -> dict[str, Any]:
    """Every case's answer, as JSON values."""
    found: dict[str, Any] = {}
    for name, body in requests():
        response = service.client.post("/lift", json=body)
        assert response.status_code == 200, (name, response.text[:300])
        found[f"http {name}"] = response.json()
    request = lifter_pb2.LiftRequest(
        poses=[lifter_pb2.Pose2D(keypoints=p.ravel().tolist()) for p in walk(5, seed=6)]
    )
    found["grpc Lift"] = MessageToDict(service.stub.Lift(request))
    found["grpc LiftStream"] = lock_step(service)
    return found


def differences(got: Any, want: Any, where: str = "") -> Iterator[str]:
    """Where `got` differs from `want`: a number by more than TOLERANCE, anything else at all."""
    if isinstance(want, dict) and isinstance(got, dict):
        if set(got) != set(want):
            yield f"{where}: keys {sorted(set(got) ^ set(want))}"
        for key in set(got) & set(want):
            yield from differences(got[key], want[key], f"{where}.{key}")
    elif isinstance(want, list) and isinstance(got, list):
        if len(got) != len(want):
            yield f"{where}: {len(got)} items, stored {len(want)}"
        for k, (g, w) in enumerate(zip(got, want, strict=False)):
            yield from differences(g, w, f"{where}[{k}]")
    elif isinstance(want, float | int) and isinstance(got, float | int) and not isinstance(want, bool):
        field = where.rsplit(".", 1)[-1].split("[", 1)[0]
        strict = STRICT.get(field)
        close = (
            math.isclose(got, want, rel_tol=0.0, abs_tol=strict)
            if strict is not None
            else math.isclose(got, want, rel_tol=RELATIVE, abs_tol=TOLERANCE)
        )
        if not (close or got == want):
            yield f"{where}: {got!r}, stored {want!r}"
    elif got != want:
        yield f"{where}: {got!r}, stored {want!r}"


@pytest.fixture(scope="module")
def service() -> Iterator[Temporal]:
    yield from temporal_service(load_model(Settings().model_path), Settings(grpc_port=0, intra_op_threads=1))


def test_every_transport_answers_as_stored(service: Temporal) -> None:
    stored = json.loads(gzip.decompress(GOLDEN.read_bytes()))
    found = list(differences(answers(service), stored))
    assert found == [], f"{len(found)} differences, the first: {found[:5]}"


def main() -> int:
    """Write the answers of today's code to GOLDEN (--write), or say how many differ."""
    parser = argparse.ArgumentParser(
        prog="python -m tests.service.test_golden", description=__doc__.split("\n")[0]
    )
    parser.add_argument("--write", action="store_true", help="store today's answers")
    args = parser.parse_args()
    for handle in temporal_service(
        load_model(Settings().model_path), Settings(grpc_port=0, intra_op_threads=1)
    ):
        found = answers(handle)
    if args.write:
        GOLDEN.write_bytes(gzip.compress(json.dumps(found, sort_keys=True).encode(), mtime=0))
        print(f"wrote {GOLDEN} ({GOLDEN.stat().st_size / 1024:.0f} KB)")
        return 0
    stored = json.loads(gzip.decompress(GOLDEN.read_bytes()))
    print(f"{len(list(differences(found, stored)))} differences")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
