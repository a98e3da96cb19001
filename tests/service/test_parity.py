"""The parity table: each input shape a user has x each interface. Every cell gives the 3D answer the
plain HTTP request of the same poses in pixels gives (the reference), or a field-level error that names
the fix. Where a shape means nothing on an interface (a file over gRPC), the cell is the documented
conversion path, said in CELLS."""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import grpc
import httpx
import numpy as np
import pytest

from repnet._proto.repnet.v1 import lifter_pb2, lifter_pb2_grpc
from repnet.cli.main import EXIT_OK, main
from repnet.client.http import LiftClient, build_request
from repnet.client.stream import Frame, StreamClient
from repnet.core.formats import FORMATS, MODEL_JOINTS, from_model_joints
from repnet.io.pose_file import read_input
from repnet.runtime.replies import IMPLAUSIBLE_BELOW
from tests.conftest import POSE_2D, POSE_3D, LiveService, project
from tests.service import test_page
from tests.service.detector_files import BUILDERS, Expected
from tests.service.page_examples import detector_pose
from tests.service.test_page import (
    assert_numbers_match,
    lifts,
    open_page,
    page_mode,
    shown_numbers,
    wait_lift,
)

driver = test_page.driver  # the page tests' chromium, a fixture

SIZE = (1280.0, 720.0)  # the image MediaPipe's landmarks are normalised by


@dataclass(frozen=True)
class Shape:
    """An input as a user has it: its poses in pixels (N, J, 2) (NaN: missing), confidence, format,
    and how it is written to a file (`write(folder) -> the path repnet lift and the page read`)."""

    name: str
    points: np.ndarray
    confidence: np.ndarray | None
    format: str
    write: Callable[[Path], Path]
    # The poses the reference lifts, where they differ from `points`: exact (0, 0) joints of pairs
    # without confidence are missing (the input rule of repnet.core.keypoints), on every interface.
    same_as: np.ndarray | None = None
    image_size: tuple[float, float] | None = None  # what x, y are normalised by (--image-size, the page's)
    raw: bool = False  # a detector's own JSON file: posted whole to /lift, it is told what it is


def _json(name: str, data: Any) -> Callable[[Path], Path]:
    def write(folder: Path) -> Path:
        (path := folder / name).write_text(json.dumps(data))
        return path

    return write


def _shapes() -> list[Shape]:
    conf = np.linspace(0.95, 0.6, 17).round(2)
    coco = detector_pose("coco17", 40.0)
    body = np.stack([detector_pose("body25", y) for y in (-20.0, 10.0)])
    op_conf = np.full(body.shape[:2], 0.9)
    op_conf[1, 4], body[1, 4] = 0.0, np.nan  # OpenPose's 0, 0, 0: a joint it did not find
    landmarks, found = from_model_joints(FORMATS["mediapipe33"], project(POSE_3D, 30.0)[None])
    media = np.where(found[0][:, None], landmarks[0], landmarks[0, 0]).round(1)  # the face at the nose
    mpii = np.stack([detector_pose("mpii16", y) for y in (-20.0, 50.0)])
    mpii[0, 15] = np.nan
    zeroed = POSE_2D.copy()
    zeroed[3] = 0.0  # a right ankle the detector did not find, written as 0, 0

    def openpose(folder: Path) -> Path:
        (frames := folder / "openpose").mkdir()
        for i, (pose, c) in enumerate(zip(body, op_conf, strict=True)):
            flat = np.concatenate([np.nan_to_num(pose), c[:, None]], axis=1).ravel().tolist()
            (frames / f"clip_{i:012d}_keypoints.json").write_text(
                json.dumps({"version": 1.3, "people": [{"person_id": [-1], "pose_keypoints_2d": flat}]})
            )
        return frames

    def npz(folder: Path) -> Path:
        np.savez(path := folder / "poses.npz", keypoints=mpii, format=np.array("mpii16"))
        return path

    b25b = np.stack([detector_pose("body25b", y) for y in (-30.0, 20.0)])  # OpenPose BODY_25B
    body25b_body = {"format": "body25b", "poses": [{"keypoints": p.tolist()} for p in b25b]}
    rows = [[x / SIZE[0], y / SIZE[1], -0.1, 0.9] for x, y in media.tolist()]
    triples = np.concatenate([POSE_2D, conf[:, None]], axis=1).tolist()
    scored = np.concatenate([coco, np.full((17, 1), 0.8)], axis=1).ravel().tolist()
    results = [{"image_id": 7, "category_id": 1, "score": 0.9, "keypoints": scored}]
    return [
        Shape("h36m17 pairs", POSE_2D[None], None, "h36m17", _json("pairs.json", POSE_2D.tolist())),
        Shape("triplets", POSE_2D[None], conf[None], "h36m17", _json("triplets.json", triples)),
        Shape("coco results", coco[None], np.full((1, 17), 0.8), "coco17", _json("results.json", results)),
        Shape("openpose folder", body, op_conf, "body25", openpose),
        Shape(
            "mediapipe rows",
            media[None],
            np.full((1, 33), 0.9),
            "mediapipe33",
            _json(
                "mediapipe.json",
                {"poses": [{"keypoints": rows}], "format": "mediapipe33", "image_size": SIZE},
            ),
        ),  # fmt: skip
        Shape("npz", mpii, None, "mpii16", npz),
        Shape("body25b body", b25b, None, "body25b", _json("body25b.json", body25b_body)),
        Shape(
            "pairs with (0, 0)",
            zeroed[None],
            None,
            "h36m17",
            _json("zeros.json", zeroed.tolist()),
            np.where(np.arange(17)[:, None] == 3, np.nan, zeroed)[None],
        ),  # fmt: skip
    ]


def _detector_shape(name: str, read: str) -> Shape:
    """A detector's file (tests/fixtures/detectors), written as its tool writes it."""
    want: Expected = BUILDERS[name]()

    def write(folder: Path) -> Path:
        for file, text in want.files.items():
            (folder / file).parent.mkdir(parents=True, exist_ok=True)
            (folder / file).write_text(text)
        return folder / read

    raw = read.endswith(".json")
    return Shape(name, want.points, want.confidence, want.format, write, image_size=want.image_size, raw=raw)


# The detectors' files (issue 31): each read as its tool writes it, by repnet lift and the page.
DETECTOR_SHAPES = {"mmpose video": "mmpose_video.json", "mmpose image": "mmpose_image.json",
                   "yolo summary": "yolo_summary.json", "yolo labels": "yolo_labels",
                   "mediapipe results": "mediapipe_python.json", "alphapose": "alphapose-results.json",
                   "coco wholebody": "coco_wholebody.json",
                   "openpose coco18": "openpose_coco18_000000000000_keypoints.json"}  # fmt: skip


def _mmpose_images() -> Shape:
    """MMPose's pred_out_dir of an image folder: one instances file per image, read as frames."""
    want = BUILDERS["mmpose image"]()
    (item,) = json.loads(want.files["mmpose_image.json"])
    points = np.stack([want.points[0], want.points[0] + [40.0, -10.0]])
    conf = np.concatenate([want.confidence, want.confidence[:, ::-1]])  # type: ignore[index]

    def write(folder: Path) -> Path:
        (images := folder / "predictions").mkdir()
        for i, (p, c) in enumerate(zip(points, conf, strict=True)):
            instance = {**item, "keypoints": p.tolist(), "keypoint_scores": c.tolist()}
            (images / f"frame_{i:04d}.json").write_text(json.dumps([instance]))
        return images

    return Shape("mmpose image folder", points, conf, want.format, write)


SHAPES = {s.name: s for s in [*_shapes(), _mmpose_images()]} | {
    n: _detector_shape(n, f) for n, f in DETECTOR_SHAPES.items()
}
# How each interface takes each shape: "direct" where it reads the shape as the user has it, else
# the documented conversion path (README "Input formats").
CELLS: dict[str, dict[str, str]] = {
    "http": {
        "h36m17 pairs": "direct",
        "triplets": "direct",
        "mediapipe rows": "direct (image_size)",
        "coco results": "posted raw: 422 detector_output naming `repnet lift` and coco17; else each "
        "result's keypoints as [x, y, score] rows with format coco17",
        "openpose folder": "a frame posted raw: 422 detector_output naming body25; else each "
        "pose_keypoints_2d as [x, y, c] rows with format body25",
        "npz": "the client reads it: np.load(...)['keypoints'] rows (NaN -> null)",
        "body25b body": "direct",
        "pairs with (0, 0)": "direct: (0, 0) is missing, with a warning",
        "mmpose image folder": "each file's instances as rows with format halpe26 (a file posted raw: "
        "422 detector_output)",
        **{
            name: "the file posted raw: 422 detector_output naming what it is, `repnet lift` and its format; "
            "else each pose's keypoints as [x, y] rows (in pixels) with its confidence and format"
            for name in DETECTOR_SHAPES
        },
    },  # fmt: skip
    "grpc unary": {
        "h36m17 pairs": "direct",
        "triplets": "x, y in keypoints, c in confidence (flat triplets: "
        "INVALID_ARGUMENT naming `confidence`)",
        "mediapipe rows": "normalised x, y with image_size, visibility in confidence",
        "coco results": "per result: x, y and scores",
        "openpose folder": "per person: x, y and c",
        "npz": "the array's rows",
        "body25b body": "direct",
        "pairs with (0, 0)": "direct: (0, 0) is missing, with a warning",
        "mmpose image folder": "per pose: x, y and the keypoint scores",
        **{
            name: "per pose: x, y in pixels and the confidence (read_input reads the file)"
            for name in DETECTOR_SHAPES
        },
    },  # fmt: skip
    "grpc stream": {
        name: "StreamClient frames of (J, 2) or (J, 3) [x, y, c] arrays (read_input for files)"
        for name in SHAPES
    },  # fmt: skip
    "python client": {
        name: "LiftClient.lift_batch of (N, J, 2) or (N, J, 3) arrays; files through "
        "repnet.io.pose_file.read_input, as repnet lift reads them"
        for name in SHAPES
    },  # fmt: skip
    "cli": {name: "repnet lift FILE (--temporal off: each pose alone, as the reference)" for name in SHAPES},
}


def reference(url: str, shape: Shape) -> np.ndarray:
    """answers() of the poses in pixels, POSTed as plain rows."""
    points = shape.points if shape.same_as is None else shape.same_as
    body = build_request(points, shape.confidence, shape.format)
    reply = httpx.post(f"{url}/lift", json=body, timeout=30)
    assert reply.status_code == 200, reply.text
    return answers(reply.json()["poses"])


def answers(poses: list[Any]) -> np.ndarray:
    """(N, 17, 5) each pose's pose_3d (mm) beside its reprojection (px): the 3D answer is the same for
    any scale of the input, its reprojection is not."""
    return np.array([np.concatenate([p["pose_3d"], p["reprojection"]], axis=1) for p in poses])


def rows_of(points: np.ndarray, conf: np.ndarray | None) -> list[Any]:
    return [None if np.isnan(p).any() else (p.tolist() if conf is None else [*p, c]) for p, c in
            zip(points, conf if conf is not None else [None] * len(points), strict=True)]  # fmt: skip


def via_http(live: LiveService, shape: Shape, folder: Path) -> np.ndarray:
    url = f"{live.http_url}/lift"
    if shape.name == "mediapipe rows":
        body = json.loads(shape.write(folder).read_text())
    elif shape.name in ("coco results", "openpose folder") or shape.raw:
        path = shape.write(folder)
        raw = json.loads((sorted(path.glob("*.json"))[0] if path.is_dir() else path).read_text())
        error = httpx.post(url, json=raw, timeout=30)
        (item,) = error.json()["detail"]
        assert (
            error.status_code == 422 and item["code"] == "detector_output" and "repnet lift" in item["reason"]
        )
        assert f'"{shape.format}"' in item["reason"], item
        conf = [None] * len(shape.points) if shape.confidence is None else shape.confidence
        body = {"format": shape.format, "poses": [{"keypoints": rows_of(p, c)} for p, c in
                zip(shape.points, conf, strict=True)]}  # fmt: skip
    else:
        conf = [None] * len(shape.points) if shape.confidence is None else shape.confidence
        body = {"format": shape.format, "poses": [{"keypoints": rows_of(p, c)} for p, c in
                zip(shape.points, conf, strict=True)]}  # fmt: skip
    reply = httpx.post(url, json=body, timeout=30)
    assert reply.status_code == 200, reply.text
    return answers(reply.json()["poses"])


def via_grpc_unary(live: LiveService, shape: Shape, folder: Path) -> np.ndarray:
    stub = lifter_pb2_grpc.PoseLifterStub(channel := grpc.insecure_channel(live.grpc_target))  # type: ignore[no-untyped-call]
    try:
        request = lifter_pb2.LiftRequest(format=shape.format)
        for i, points in enumerate(shape.points):
            missing = np.isnan(points).any(axis=1)
            pose = request.poses.add(
                keypoints=np.nan_to_num(points).ravel().tolist(), missing=missing.tolist()
            )
            if shape.confidence is not None:
                pose.confidence.extend(shape.confidence[i].tolist())
            if shape.name == "mediapipe rows":
                del pose.keypoints[:]
                pose.keypoints.extend((points / SIZE).ravel().tolist())
                pose.image_size.width, pose.image_size.height = SIZE
        if shape.name == "triplets":  # the flat triplets a detector writes: told where c goes
            flat = lifter_pb2.LiftRequest(poses=[lifter_pb2.Pose2D(keypoints=np.ravel(
                np.concatenate([shape.points[0], shape.confidence.T], axis=1)).tolist())])  # type: ignore[union-attr]  # fmt: skip
            with pytest.raises(grpc.RpcError) as info:
                stub.Lift(flat, timeout=30)
            assert info.value.code() == grpc.StatusCode.INVALID_ARGUMENT
            assert "poses[0].keypoints" in info.value.details() and "`confidence`" in info.value.details()
        reply = stub.Lift(request, timeout=30)
    finally:
        channel.close()
    shaped = [{"pose_3d": np.reshape(p.pose_3d, (17, 3)), "reprojection": np.reshape(p.reprojection, (17, 2))}
              for p in reply.poses]  # fmt: skip
    return answers(shaped)


def _arrays(shape: Shape, folder: Path) -> tuple[np.ndarray, str]:
    """A file's poses as the Python clients take them: (N, J, 3) [x, y, c] or (N, J, 2) arrays."""
    poses = read_input(str(shape.write(folder)), lambda files: files, shape.image_size)
    fmt = poses.format or shape.format
    if poses.confidence is None:
        return poses.points, fmt
    return np.concatenate([poses.points, poses.confidence[..., None]], axis=-1), fmt


def via_grpc_stream(live: LiveService, shape: Shape, folder: Path) -> np.ndarray:
    arrays, fmt = _arrays(shape, folder)
    with StreamClient(live.grpc_target, timeout=30) as client:
        results = list(client.stream([Frame(a) for a in arrays], format=fmt))
    assert all(r.error is None for r in results), [r.error for r in results]
    return answers([vars(r.result) for r in results if r.result is not None])


def via_python_client(live: LiveService, shape: Shape, folder: Path) -> np.ndarray:
    arrays, fmt = _arrays(shape, folder)
    with LiftClient(live.http_url) as client:
        if len(arrays) == 1:
            return answers([vars(client.lift(arrays[0], format=fmt))])
        return answers([vars(r) for r in client.lift_batch(arrays, format=fmt)])


def via_cli(live: LiveService, shape: Shape, folder: Path) -> np.ndarray:
    out = folder / "out.json"
    args = ["lift", str(shape.write(folder)), "--url", live.http_url, "--temporal", "off", "-o", str(out)]
    if shape.image_size is not None:
        args += ["--image-size", *(str(v) for v in shape.image_size)]
    assert main(args) == EXIT_OK
    return answers(json.loads(out.read_text())["poses"])


INTERFACES = {"http": via_http, "grpc unary": via_grpc_unary, "grpc stream": via_grpc_stream,
              "python client": via_python_client, "cli": via_cli}  # fmt: skip


@pytest.fixture(scope="module")
def references(live_service: LiveService) -> dict[str, np.ndarray]:
    return {name: reference(live_service.http_url, shape) for name, shape in SHAPES.items()}


@pytest.mark.parametrize("interface", list(INTERFACES))
@pytest.mark.parametrize("shape", list(SHAPES))
def test_every_input_shape_gives_the_same_answer_on_every_interface(
    live_service: LiveService, references: dict[str, np.ndarray], tmp_path: Path, shape: str, interface: str
) -> None:
    assert CELLS[interface][shape]  # every cell says how the interface takes the shape
    got = INTERFACES[interface](live_service, SHAPES[shape], tmp_path)
    want = references[shape]
    assert got.shape == want.shape
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-3)


def test_zero_joints_are_missing_with_the_same_warning_on_every_interface(live_service: LiveService) -> None:
    points = SHAPES["pairs with (0, 0)"].points
    http = httpx.post(f"{live_service.http_url}/lift", json={"keypoints": points[0].tolist()}, timeout=30)
    with LiftClient(live_service.http_url) as client:
        python = client.lift(points[0])
    with StreamClient(live_service.grpc_target, timeout=30) as stream:
        (unary,) = stream.lift_batch(points)
        (frame,) = stream.stream([points[0]])
    assert frame.result is not None
    warnings = [http.json()["poses"][0]["warnings"], list(python.warnings), list(unary.warnings),
                list(frame.result.warnings)]  # fmt: skip
    assert all(w == warnings[0] for w in warnings) and len(warnings[0]) == 1
    assert warnings[0][0].startswith("keypoints: 1 joint at exactly (0, 0) without confidence counted as")


def _stretched_arm() -> np.ndarray:
    """POSE_2D with the left arm three times its length: an answer the bundled model's plausibility
    puts below IMPLAUSIBLE_BELOW (0.007)."""
    pose = POSE_2D.copy()
    shoulder, elbow, wrist = (MODEL_JOINTS.index(f"left_{j}") for j in ("shoulder", "elbow", "wrist"))
    pose[elbow] = pose[shoulder] + 3.0 * (POSE_2D[elbow] - POSE_2D[shoulder])
    pose[wrist] = pose[elbow] + 3.0 * (POSE_2D[wrist] - POSE_2D[elbow])
    return pose


def test_an_implausible_pose_gets_the_same_warning_on_every_interface(
    live_service: LiveService, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    pose = _stretched_arm()
    http = httpx.post(f"{live_service.http_url}/lift", json={"keypoints": pose.tolist()}, timeout=30).json()
    with LiftClient(live_service.http_url) as client:
        python = client.lift(pose)
    with StreamClient(live_service.grpc_target, timeout=30) as stream:
        (unary,) = stream.lift_batch(pose[None])
        (frame,) = stream.stream([pose])
    assert frame.result is not None
    source = tmp_path / "pose.json"
    source.write_text(json.dumps(pose.tolist()))
    lifted = []
    for where in (["--url", live_service.http_url], ["--local"]):
        out = tmp_path / f"out{len(lifted)}.json"
        assert main(["lift", str(source), *where, "-o", str(out)]) == EXIT_OK
        lifted.append(json.loads(out.read_text())["poses"][0]["warnings"])
    err = capsys.readouterr().err
    warnings = [http["poses"][0]["warnings"], list(python.warnings), list(unary.warnings),
                list(frame.result.warnings), *lifted]  # fmt: skip
    assert all(w == warnings[0] for w in warnings) and len(warnings[0]) == 1
    plausibility = http["poses"][0]["plausibility"]
    assert plausibility < IMPLAUSIBLE_BELOW
    assert warnings[0][0] == (
        f"plausibility: the 3D pose looks implausible (plausibility {plausibility:.3g} < "
        f"{IMPLAUSIBLE_BELOW:g}, below 99 % of the answers to real people's 2D): check the format and "
        "the keypoints"
    )
    assert f"warning: 1 of 1 poses: {warnings[0][0]}" in err
    normal = httpx.post(
        f"{live_service.http_url}/lift", json={"keypoints": POSE_2D.tolist()}, timeout=30
    ).json()
    assert normal["poses"][0]["warnings"] == [] and normal["poses"][0]["plausibility"] >= IMPLAUSIBLE_BELOW


# The page's cells: each shape as a user gives it to the page (pasted text or picked files), lifted
# with the temporal control off (each pose alone, as the reference), its numbers those of the API.
PAGE_INPUTS = {"h36m17 pairs": "paste", "triplets": "paste", "coco results": "file",
               "openpose folder": "files", "mediapipe rows": "paste", "npz": "file",
               "pairs with (0, 0)": "paste", "mmpose video": "file", "mmpose image": "paste",
               "yolo summary": "file", "yolo labels": "files", "mediapipe results": "file",
               "alphapose": "file", "coco wholebody": "paste", "openpose coco18": "files",
               "mmpose image folder": "files", "body25b body": "file"}  # fmt: skip


@pytest.mark.parametrize("shape", list(PAGE_INPUTS))
def test_the_page_gives_the_same_answer_for_every_shape_it_reads(
    driver: Any, live_service: LiveService, tmp_path: Path, shape: str
) -> None:
    from selenium.webdriver.common.by import By

    path = SHAPES[shape].write(tmp_path)
    points = SHAPES[shape].points if SHAPES[shape].same_as is None else SHAPES[shape].same_as
    body = build_request(points, SHAPES[shape].confidence, SHAPES[shape].format)
    reply = httpx.post(f"{live_service.http_url}/lift", json=body, timeout=30).json()
    open_page(driver, live_service.http_url)
    driver.execute_script("document.getElementById('temporal').value = 'off'")
    if SHAPES[shape].image_size is not None:  # the size the file's x, y are normalised by
        size = ", ".join(f"{v:g}" for v in SHAPES[shape].image_size)
        driver.execute_script("document.getElementById('image-size').value = arguments[0]", size)
    before = lifts(driver)
    if PAGE_INPUTS[shape] == "paste":
        driver.execute_script("document.getElementById('paste').value = arguments[0]", path.read_text())
        driver.find_element(By.ID, "lift-paste").click()
    else:
        files = sorted(path.glob("*.json")) or sorted(path.glob("*.txt")) if path.is_dir() else [path]
        driver.find_element(By.ID, "file").send_keys("\n".join(str(f) for f in files))
    wait_lift(driver, before)
    assert_numbers_match(shown_numbers(driver), reply["poses"][0], reply["joints"])
    assert page_mode(driver) == "off"


# The page's reader on its own: parse.js and detectors.js, run in chromium on each detector's file,
# give the poses, frames and people repnet lift reads (pixels: normalised x, y times the image size).
PAGE_READ = """
const [files, done] = [arguments[0], arguments[arguments.length - 1]];
import("/ui/parse.js").then((parse) => parse.parseFiles(files.map(([name, text]) => new File([text], name))))
  .then((r) => done({poses: r.poses, frames: r.frames, people: r.people, normalised: r.normalised ?? null}),
        (err) => done({error: String(err)}));
"""


def _page_poses(
    read: dict[str, Any], size: tuple[float, float] | None
) -> tuple[np.ndarray, np.ndarray | None]:
    """The page's /lift poses as (N, J, 2) px (NaN: missing) and (N, J) confidence (None: none)."""
    scale = np.asarray(size if read["normalised"] else (1.0, 1.0))
    points = np.array([[[np.nan] * 2 if r is None else r[:2] for r in p["keypoints"]] for p in read["poses"]])
    conf = [p.get("confidence") or ([r[3] for r in p["keypoints"]] if len(p["keypoints"][0]) == 4 else None)
            for p in read["poses"]]  # fmt: skip
    return points * scale, None if conf[0] is None else np.array(conf, dtype=np.float64)


@pytest.mark.parametrize("shape", [*DETECTOR_SHAPES, "mmpose image folder"])
def test_the_page_reads_each_detector_file_as_repnet_lift_does(
    driver: Any, live_service: LiveService, tmp_path: Path, shape: str
) -> None:
    path = SHAPES[shape].write(tmp_path)
    files = sorted(path.glob("*.json")) or sorted(path.glob("*.txt")) if path.is_dir() else [path]
    open_page(driver, live_service.http_url)
    read = driver.execute_async_script(PAGE_READ, [[f.name, f.read_text()] for f in files])
    assert "error" not in read, read
    poses = read_input(str(path), lambda found: found, SHAPES[shape].image_size)
    assert (read["frames"], read["people"]) == (poses.frame.tolist(), poses.person.tolist())
    assert {p.get("format") for p in read["poses"]} == {poses.format}
    points, conf = _page_poses(read, SHAPES[shape].image_size)
    np.testing.assert_allclose(points, poses.points, rtol=1e-12)
    if poses.confidence is None:
        assert conf is None
    else:
        np.testing.assert_allclose(np.asarray(conf), poses.confidence)
