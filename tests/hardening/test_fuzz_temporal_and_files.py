"""Property fuzzing (hypothesis) where schemathesis does not reach (issue 30): POST /lift's temporal
fields (mode, fps, track ids, frame numbers of any size) against a live service with its temporal
models, and the CLI's file readers on arbitrary JSON values and NPZ arrays. Each input is answered
or refused by name: never a 5xx, never an exception other than the reader's InputFileError."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import httpx
import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from repnet.io.pose_file import load_poses
from repnet.io.poses import InputFileError
from tests.conftest import POSE_2D, LiveService

FUZZ = settings(max_examples=60, deadline=None, database=None, suppress_health_check=list(HealthCheck))
BIG_INTS = st.one_of(
    st.integers(-(2**70), 2**70), st.integers(0, 40), st.sampled_from([2**53 - 1, 2**53, 2**63])
)
NUMBERS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True), BIG_INTS, st.booleans(), st.none(), st.text(max_size=4)
)
TRACK_IDS = st.one_of(
    st.text(max_size=140), st.integers(), st.none(), st.sampled_from(["a", "../x", "a\x00b", ""])
)


@st.composite
def temporal_bodies(draw: st.DrawFn) -> dict[str, Any]:
    count = draw(st.integers(1, 12))
    poses = []
    for _ in range(count):
        pose: dict[str, Any] = {"keypoints": (POSE_2D + draw(st.floats(-50, 50))).round(1).tolist()}
        if draw(st.booleans()):
            pose["track_id"] = draw(TRACK_IDS)
        if draw(st.booleans()):
            pose["frame"] = draw(st.one_of(BIG_INTS, NUMBERS))
        poses.append(pose)
    body: dict[str, Any] = {"poses": poses}
    body["temporal"] = draw(
        st.one_of(st.sampled_from(["causal", "offline", "off"]), st.text(max_size=8), NUMBERS)
    )
    if draw(st.booleans()):
        body["fps"] = draw(st.one_of(st.floats(-1e9, 1e9), NUMBERS))
    return body


@given(body=temporal_bodies())
@FUZZ
def test_temporal_fields_are_answered_or_refused_by_name(
    live_service: LiveService, body: dict[str, Any]
) -> None:
    text = json.dumps(body, allow_nan=True)  # NaN and Infinity as Python writes them: refused, not a 500
    headers = {"content-type": "application/json"}
    reply = httpx.post(f"{live_service.http_url}/lift", content=text, headers=headers, timeout=60)
    assert reply.status_code in (200, 422), (reply.status_code, reply.text[:300], text[:300])
    answer = reply.json()
    if reply.status_code == 422:
        assert answer["detail"] and all(item["field"] and item["reason"] for item in answer["detail"]), answer
    else:
        assert len(answer["poses"]) == len(body["poses"])


def read_or_refused(path: Path) -> None:
    """load_poses gives (N, J, 2) points, or refuses with an InputFileError naming the file."""
    try:
        poses = load_poses(path)
    except InputFileError as err:
        refused = str(err)
    else:
        assert poses.points.ndim == 3 and poses.points.shape[-1] == 2
        return
    assert path.name in refused, refused


JSON_VALUES = st.recursive(
    st.one_of(NUMBERS, st.text(max_size=6)),
    lambda inner: st.one_of(st.lists(inner, max_size=20), st.dictionaries(
        st.sampled_from(["keypoints", "poses", "people", "pose_keypoints_2d", "format", "fps", "frame",
                         "track_id", "confidence", "x", "y", "frame_id", "instances", "keypoint_scores",
                         "box", "visible", "pose_landmarks", "landmarks", "image_id", "foot_kpts",
                         "annotations"]), inner, max_size=5)),
    max_leaves=60,
)  # fmt: skip
DETECTOR_FILES = sorted((Path(__file__).resolve().parents[1] / "fixtures" / "detectors").glob("*.json"))


@given(value=JSON_VALUES)
@FUZZ
def test_any_json_value_is_read_or_refused_with_the_files_name(tmp_path_factory: Any, value: Any) -> None:
    path = tmp_path_factory.mktemp("fuzz") / "input.json"
    path.write_text(json.dumps(value, allow_nan=True))
    read_or_refused(path)


@st.composite
def mutated_detector_files(draw: st.DrawFn) -> Any:
    """A detector's file (tests/fixtures/detectors) with one value somewhere in it replaced."""
    data = json.loads(draw(st.sampled_from(DETECTOR_FILES)).read_text())
    parent, key = None, None
    node = data
    while isinstance(node, list | dict) and node and draw(st.integers(0, 5)) > 0:
        keys = list(range(len(node))) if isinstance(node, list) else list(node)
        parent, key = node, draw(st.sampled_from(keys))
        node = node[key]
    replacement = draw(JSON_VALUES)
    if parent is None:
        return replacement
    parent[key] = replacement
    return data


@given(value=mutated_detector_files())
@FUZZ
def test_any_detector_file_changed_is_read_or_refused_with_the_files_name(
    tmp_path_factory: Any, value: Any
) -> None:
    path = tmp_path_factory.mktemp("fuzz") / "input.json"
    path.write_text(json.dumps(value, allow_nan=True))
    read_or_refused(path)


LABEL_TOKENS = st.one_of(st.floats(allow_nan=True, allow_infinity=True).map(str), st.integers().map(str),
                         st.sampled_from(["0", "0.5", "1", "x", "", "1e400", "-0"]))  # fmt: skip


LABEL_LINES = st.sampled_from([0, 5, 39, 40, 41, 42, 56, 57, 58, 59]).flatmap(
    lambda n: st.lists(LABEL_TOKENS, min_size=n, max_size=n).map(" ".join)
)  # YOLO-pose line lengths: 17 keypoints of 2 or 3 values after the box, 0 to 2 values after them


@given(lines=st.lists(LABEL_LINES, max_size=4))
@FUZZ
def test_any_yolo_label_file_is_read_or_refused_with_the_files_name(
    tmp_path_factory: Any, lines: list[str]
) -> None:
    path = tmp_path_factory.mktemp("fuzz") / "frame_3.txt"
    path.write_text("\n".join(lines))
    read_or_refused(path)


ARRAYS = st.one_of(
    st.tuples(st.integers(0, 4), st.integers(0, 20), st.integers(0, 5)).map(lambda s: np.full(s, 1.5)),
    st.tuples(st.integers(0, 20), st.integers(0, 5)).map(lambda s: np.zeros(s)),
    st.sampled_from([np.array("text"), np.array([1, 2], dtype=np.int8),
                     np.array([math.nan] * 34).reshape(17, 2), np.array([[True] * 2] * 17),
                     np.zeros((2, 17, 2), dtype=np.complex64)]),
)  # fmt: skip


EXTRAS = st.sampled_from([{}, {"format": np.array("coco17")}, {"fps": np.array([1, 2])},
                          {"confidence": np.zeros(3)}, {"format": np.array(5)}])  # fmt: skip


@given(keypoints=ARRAYS, extra=EXTRAS)
@FUZZ
def test_any_npz_is_read_or_refused_with_the_files_name(
    tmp_path_factory: Any, keypoints: np.ndarray, extra: dict[str, np.ndarray]
) -> None:
    path: Path = tmp_path_factory.mktemp("fuzz") / "input.npz"
    np.savez(path, keypoints=keypoints, **extra)
    read_or_refused(path)
