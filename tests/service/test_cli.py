"""End-to-end tests of the `repnet` command: lift files locally and via the service, plot, formats."""

from __future__ import annotations

import io
import json
import shutil
import socket
import time
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from repnet.cli import local
from repnet.cli import main as cli
from repnet.cli.lift import stills_reason
from repnet.cli.main import (
    EXIT_OK,
    EXIT_REJECTED,
    EXIT_UNREACHABLE,
    EXIT_USAGE,
    load_poses,
    main,
    progress_bar,
)
from repnet.core.formats import FORMATS, MODEL_JOINTS, MODEL_PARENTS, from_model_joints
from repnet.io import pose_file
from tests.conftest import POSE_2D, POSE_3D, SMALL_TEMPORAL_POSES, TEMPORAL_MODES, LiveService, project


def _coco_file(tmp_path: Path, n: int = 3) -> Path:
    """n COCO poses (turning person) as JSON, with nulls for joints the detector missed."""
    points, _ = from_model_joints(FORMATS["coco17"], np.stack([project(POSE_3D, 20.0 * i) for i in range(n)]))
    poses = [[None if np.isnan(p).any() else p.tolist() for p in pose] for pose in points]
    path = tmp_path / "coco.json"
    path.write_text(json.dumps({"format": "coco17", "keypoints": poses}))
    return path


def _h36m_npz(tmp_path: Path, n: int) -> Path:
    path = tmp_path / "poses.npz"
    np.savez(path, keypoints=np.stack([project(POSE_3D, 10.0 * i) for i in range(n)]))
    return path


def test_formats_prints_the_mapping_table(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["formats"]) == EXIT_OK
    out = capsys.readouterr().out
    assert "| 0 | pelvis | pelvis | pelvis | mid(left_hip, right_hip) | mid_hip |" in out


def test_lift_local_then_plot_writes_a_png(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out, png = tmp_path / "out.json", tmp_path / "skeleton.png"
    assert main(["lift", str(_coco_file(tmp_path)), "--local", "-o", str(out)]) == EXIT_OK
    data = json.loads(out.read_text())
    assert data["format"] == "coco17" and data["joints"] == list(MODEL_JOINTS) and len(data["poses"]) == 3
    pose = data["poses"][1]
    assert np.asarray(pose["pose_3d"]).shape == (17, 3) and np.asarray(pose["reprojection"]).shape == (17, 2)
    assert [MODEL_JOINTS[j] for j in np.flatnonzero(pose["imputed"])] == ["spine", "head"]
    assert pose["input"]["keypoints"][1] is None  # COCO left_eye: no model counterpart
    assert "lifted 3 poses" in capsys.readouterr().err

    assert main(["plot", str(out), "-o", str(png), "--index", "1"]) == EXIT_OK
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 20_000
    import matplotlib.image

    assert matplotlib.image.imread(png).shape[:2] == (550, 1600)


def test_lift_via_service_matches_local(tmp_path: Path, live_service: LiveService) -> None:
    npz = _h36m_npz(tmp_path, 5)
    remote, local = tmp_path / "remote.json", tmp_path / "local.json"
    args = ["lift", str(npz), "--batch-size", "2", "-o"]
    assert main([*args, str(remote), "--url", live_service.http_url]) == EXIT_OK
    assert main([*args, str(local), "--local"]) == EXIT_OK
    a, b = json.loads(remote.read_text()), json.loads(local.read_text())
    assert a["format"] == "h36m17" and len(a["poses"]) == len(b["poses"]) == 5
    for pa, pb in zip(a["poses"], b["poses"], strict=True):
        np.testing.assert_allclose(pa["pose_3d"], pb["pose_3d"], rtol=1e-4, atol=1e-2)
        np.testing.assert_allclose(pa["input"]["keypoints"], pb["input"]["keypoints"])


def test_intrinsics_turn_pose_3d_camera_via_service_and_locally(
    tmp_path: Path, live_service: LiveService
) -> None:
    path = tmp_path / "one.json"
    path.write_text(json.dumps((POSE_2D + [400.0, 0.0]).tolist()))  # off to the image's right
    outputs = {}
    for name, where in (
        ("plain", ["--local"]),
        ("local", ["--local"]),
        ("remote", ["--url", live_service.http_url]),
    ):
        out = tmp_path / f"{name}.json"
        camera = [] if name == "plain" else ["--intrinsics", "1145,1145,512,515"]
        assert main(["lift", str(path), *where, *camera, "-o", str(out)]) == EXIT_OK
        outputs[name] = json.loads(out.read_text())["poses"][0]
    np.testing.assert_allclose(
        outputs["local"]["pose_3d_camera"], outputs["remote"]["pose_3d_camera"], atol=1e-2
    )
    assert not np.allclose(outputs["local"]["pose_3d_camera"], outputs["plain"]["pose_3d_camera"], atol=1.0)
    np.testing.assert_allclose(outputs["local"]["pose_3d"], outputs["plain"]["pose_3d"])


@pytest.mark.parametrize("value", ["1145,1145,512", "0,1145,512,515", "a,b,c,d", "1145,1145,nan,515"])
def test_bad_intrinsics_flag_exits_2(tmp_path: Path, capsys: pytest.CaptureFixture[str], value: str) -> None:
    path = tmp_path / "one.json"
    path.write_text(json.dumps(POSE_2D.tolist()))
    with pytest.raises(SystemExit) as info:
        main(["lift", str(path), "--local", "--intrinsics", value])
    assert info.value.code == EXIT_USAGE
    assert "--intrinsics: expected FX,FY,CX,CY" in capsys.readouterr().err


def test_lift_to_stdout(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "one.json"
    path.write_text(json.dumps(POSE_2D.tolist()))
    assert main(["lift", str(path), "--local"]) == EXIT_OK
    assert len(json.loads(capsys.readouterr().out)["poses"]) == 1


def test_rejected_pose_is_named_by_its_place_in_the_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    keypoints = np.stack([POSE_2D] * 5)
    keypoints[3] = 100.0  # every joint at one point
    path = tmp_path / "bad.npz"
    np.savez(path, keypoints=keypoints)
    assert main(["lift", str(path), "--local", "--batch-size", "2", "--strict"]) == EXIT_REJECTED
    err = capsys.readouterr().err
    assert "frame 3, person 0: keypoints" in err and "one point" in err


def _openpose_file(path: Path, fmt: str) -> Path:
    points, visible = from_model_joints(FORMATS[fmt], POSE_2D[None])
    flat = np.concatenate([np.nan_to_num(points[0]), visible[0, :, None].astype(float)], axis=1).ravel()
    path.write_text(json.dumps({"version": 1.3, "people": [{"pose_keypoints_2d": flat.tolist()}]}))
    return path


def test_openpose_json_is_read_as_body25(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = _openpose_file(tmp_path / "frame_000000_keypoints.json", "body25")
    poses = load_poses(path)
    assert poses.format == "body25" and poses.points.shape == (1, 25, 2)
    assert np.isnan(poses.points[0, FORMATS["body25"].joint_names.index("left_ear")]).all()
    assert main(["lift", str(path), "--local", "-o", str(tmp_path / "out.json")]) == EXIT_OK
    # BODY_25B has 25 joints too, in another order: the reading is said, with the other choice
    err = capsys.readouterr().err
    assert "25 joints read as body25 (OpenPose BODY_25); for OpenPose BODY_25B" in err
    assert "use --format body25b" in err
    out = tmp_path / "out_b.json"
    assert main(["lift", str(path), "--local", "--format", "body25b", "-o", str(out)]) == EXIT_OK
    assert "25 joints read as" not in capsys.readouterr().err  # chosen, not guessed
    assert json.loads(out.read_text())["format"] == "body25b"


def test_openpose_coco_json_with_18_joints_is_read_as_coco18(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = _openpose_file(tmp_path / "frame_000000_keypoints.json", "coco18")
    poses = load_poses(path)
    assert poses.format == "coco18" and poses.points.shape == (1, 18, 2)
    assert main(["lift", str(path), "--local", "-o", str(out := tmp_path / "out.json")]) == EXIT_OK
    assert "joints read as" not in capsys.readouterr().err  # 18 joints: one format
    lifted = json.loads(out.read_text())
    assert lifted["format"] == "coco18" and lifted["input_joints"] == list(FORMATS["coco18"].joint_names)
    imputed = [j for j, flag in zip(lifted["joints"], lifted["poses"][0]["imputed"], strict=True) if flag]
    assert imputed == ["spine", "head"]  # OpenPose COCO's neck and nose give thorax and neck


def test_confidence_column_marks_low_joints_missing(tmp_path: Path) -> None:
    rows = np.concatenate([POSE_2D, np.full((17, 1), 0.9)], axis=1)
    rows[13, 2] = 0.05  # left wrist below the default threshold 0.2
    path = tmp_path / "conf.json"
    path.write_text(json.dumps({"keypoints": rows.tolist()}))
    out = tmp_path / "out.json"
    assert main(["lift", str(path), "--local", "-o", str(out)]) == EXIT_OK
    assert np.flatnonzero(json.loads(out.read_text())["poses"][0]["imputed"]).tolist() == [13]


@pytest.mark.parametrize(
    ("content", "extra", "message"),
    [
        (None, [], "No such file"),
        ('{"keypoints": [[1, 2], [3, "a"]]}', [], "keypoints[0][1]"),
        ("[[1, 2]]", ["--format", "coco17"], "format coco17 has 17"),
        ("not json", [], "bad.json"),
        ("[" * 100_000 + "]" * 100_000, [], "nested too deeply"),
        (
            '{"poses": [{"keypoints": [[1, 2]], "track_id": "a", "frame": ' + str(2**70) + "}]}",
            [],
            "poses[0].frame: a pose with a track_id needs its frame number, an integer from 0 to 9007199",
        ),
    ],
)
def test_bad_usage_exits_2_with_a_message(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], content: str | None, extra: list[str], message: str
) -> None:
    path = tmp_path / "bad.json"
    if content is not None:
        path.write_text(content)
    assert main(["lift", str(path), *extra]) == EXIT_USAGE
    assert message in capsys.readouterr().err


def test_files_that_would_take_the_machines_memory_are_refused_before_loading(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Issue 30: a 1 MB NPZ inflating to 1.09 GB OOM-killed the CLI; a 200 MB JSON took 3.85 GB."""
    bomb = tmp_path / "bomb.npz"  # 544 MB of zeros in a file of about 0.5 MB
    with zipfile.ZipFile(bomb, "w", zipfile.ZIP_DEFLATED) as archive:
        with archive.open("keypoints.npy", "w", force_zip64=True) as member:
            for _ in range(544):
                member.write(bytes(1 << 20))
    assert bomb.stat().st_size < 4 << 20
    assert main(["lift", str(bomb), "--local"]) == EXIT_USAGE
    err = capsys.readouterr().err
    assert "bomb.npz: its arrays hold 570425344 bytes once inflated, more than 536870912" in err
    monkeypatch.setattr(pose_file, "MAX_JSON_BYTES", 1000)
    big = tmp_path / "big.json"
    big.write_text(json.dumps({"keypoints": POSE_2D.tolist(), "pad": "x" * 1000}))
    assert main(["lift", str(big), "--local"]) == EXIT_USAGE
    assert "big.json: 1" in capsys.readouterr().err  # its size named, and the way out (.npz)
    fake = tmp_path / "fake.npz"
    fake.write_text("not a zip")
    assert main(["lift", str(fake), "--local"]) == EXIT_USAGE
    assert "fake.npz: not an NPZ file" in capsys.readouterr().err


def test_missing_model_exits_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    args = ["lift", str(_coco_file(tmp_path)), "--local", "--model", str(tmp_path / "none.onnx")]
    assert main(args) == EXIT_USAGE
    assert "model file not found" in capsys.readouterr().err


def test_unreachable_service_exits_3(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        url = f"http://127.0.0.1:{s.getsockname()[1]}"
    assert main(["lift", str(_coco_file(tmp_path)), "--url", url, "--timeout", "2"]) == EXIT_UNREACHABLE
    assert "cannot reach" in capsys.readouterr().err


def test_plot_rejects_a_file_that_is_not_a_lift_output(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["plot", str(_coco_file(tmp_path)), "-o", str(tmp_path / "x.png")]) == EXIT_USAGE
    assert "not a `repnet lift` output" in capsys.readouterr().err
    assert not (tmp_path / "x.png").exists()


def _openpose_frame(path: Path, people: list[np.ndarray]) -> None:
    """An OpenPose --write_json frame: (25, 2) BODY_25 points per person, NaN = not detected (c 0)."""
    rows = [np.concatenate([np.nan_to_num(p), (~np.isnan(p).any(axis=1))[:, None] * 0.9], axis=1)
            for p in people]  # fmt: skip
    found = [{"pose_keypoints_2d": r.ravel().tolist()} for r in rows]
    path.write_text(json.dumps({"version": 1.3, "people": found}))


def _body25(shift: float) -> np.ndarray:
    points, _ = from_model_joints(FORMATS["body25"], (POSE_2D + [shift, 0.0])[None])
    return points[0].astype(np.float64)


def _openpose_folder(tmp_path: Path) -> Path:
    """Frames 1 (two people), 2 (nobody) and 10 (one person), named so that name order is wrong."""
    folder = tmp_path / "openpose"
    folder.mkdir()
    _openpose_frame(folder / "clip_10_keypoints.json", [_body25(100.0)])
    _openpose_frame(folder / "clip_1_keypoints.json", [_body25(0.0), _body25(800.0)])
    _openpose_frame(folder / "clip_2_keypoints.json", [])
    return folder


@pytest.mark.parametrize("pattern", ["", "clip_*_keypoints.json"], ids=["folder", "glob"])
def test_lift_reads_openpose_frames_by_frame_number_with_every_person(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], pattern: str
) -> None:
    folder, out = _openpose_folder(tmp_path), tmp_path / "out.json"
    source = str(folder / pattern) if pattern else str(folder)
    assert main(["lift", source, "--local", "-o", str(out)]) == EXIT_OK
    data = json.loads(out.read_text())
    assert data["format"] == "body25"
    assert [(p["frame"], p["person"]) for p in data["poses"]] == [(1, 0), (1, 1), (10, 0)]
    pelvis = FORMATS["body25"].joint_names.index("mid_hip")
    xs = [p["input"]["keypoints"][pelvis][0] for p in data["poses"]]
    np.testing.assert_allclose(xs, [POSE_2D[0, 0], POSE_2D[0, 0] + 800, POSE_2D[0, 0] + 100], atol=1e-3)
    assert "lifted 3 poses of 2 frames" in capsys.readouterr().err


def test_a_missing_joint_is_echoed_as_missing(tmp_path: Path) -> None:
    """Joints OpenPose did not detect (c = 0) and null rows: null keypoint and null confidence."""
    path, out = tmp_path / "frame_000000000007_keypoints.json", tmp_path / "out.json"
    _openpose_frame(path, [_body25(0.0), _body25(300.0)])
    assert main(["lift", str(path), "--local", "-o", str(out)]) == EXIT_OK
    poses = json.loads(out.read_text())["poses"]
    assert [(p["frame"], p["person"]) for p in poses] == [(7, 0), (7, 1)]
    ear = FORMATS["body25"].joint_names.index("left_ear")  # BODY_25 joint with no model counterpart
    assert poses[0]["input"]["keypoints"][ear] is None and poses[0]["input"]["confidence"][ear] is None
    assert poses[0]["input"]["confidence"][0] == pytest.approx(0.9)
    rows: list[object] = np.concatenate([POSE_2D, np.full((17, 1), 0.8)], axis=1).tolist()
    rows[4] = None
    (tmp_path / "rows.json").write_text(json.dumps({"keypoints": rows}))
    assert main(["lift", str(tmp_path / "rows.json"), "--local", "-o", str(out), "--overwrite"]) == EXIT_OK
    echoed = json.loads(out.read_text())["poses"][0]["input"]
    assert echoed["keypoints"][4] is None and echoed["confidence"][4] is None
    assert echoed["confidence"][3] == 0.8


def test_lift_warns_on_stderr_when_the_format_looks_wrong(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    coco = json.loads(_coco_file(tmp_path).read_text())
    path, out = tmp_path / "unlabelled.json", tmp_path / "out.json"
    path.write_text(json.dumps({"keypoints": coco["keypoints"]}))  # no format: read as h36m17
    assert main(["lift", str(path), "--local", "-o", str(out)]) == EXIT_OK
    err = capsys.readouterr().err
    assert "repnet: warning: 3 of 3 poses: format: these keypoints look like coco17, not h36m17" in err
    assert all(p["warnings"] for p in json.loads(out.read_text())["poses"])
    assert main(["lift", str(_coco_file(tmp_path)), "--local", "-o", str(out), "--overwrite"]) == EXIT_OK
    assert "warning" not in capsys.readouterr().err


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_progress_bar_shows_on_a_terminal_only() -> None:
    shown, hidden = _Terminal(), io.StringIO()
    for stream in (shown, hidden):
        bar = progress_bar(4, "pose", file=stream)
        bar.update(1)
        time.sleep(0.6)  # bars of short work stay hidden (delay 0.5 s)
        bar.update(3)
        bar.close()
    assert "pose" in shown.getvalue() and hidden.getvalue() == ""


def test_lift_reports_progress_over_files_and_poses(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    bars: list[tuple[int, str, list[int]]] = []

    class Bar:
        def __init__(self, total: int, unit: str) -> None:
            bars.append((total, unit, []))

        def update(self, n: int) -> None:
            bars[-1][2].append(n)

        def close(self) -> None:
            pass

        def __enter__(self) -> Bar:
            return self

        def __exit__(self, *_: object) -> None:
            pass

    monkeypatch.setattr(cli, "progress_bar", Bar)
    folder, out = _openpose_folder(tmp_path), tmp_path / "out.json"
    args = ["lift", str(folder), "--local", "--batch-size", "2", "-o", str(out), "--overwrite"]
    assert main([*args, "--temporal", "off"]) == EXIT_OK
    assert bars == [(3, "file", [1, 1, 1]), (3, "pose", [2, 1])]
    bars.clear()
    assert main([*args, "--temporal", "causal"]) == EXIT_OK  # one request holds the whole clip
    assert bars == [(3, "file", [1, 1, 1]), (3, "pose", [3])]


def test_plot_of_a_sequence_writes_an_animated_gif(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out, gif = tmp_path / "out.json", tmp_path / "walk.gif"
    assert main(["lift", str(_openpose_folder(tmp_path)), "--local", "-o", str(out)]) == EXIT_OK
    assert main(["plot", str(out), "-o", str(gif), "--fps", "5"]) == EXIT_OK
    assert "wrote" in capsys.readouterr().err
    from PIL import Image

    with Image.open(gif) as image:
        assert image.format == "GIF" and image.n_frames == 2  # person 0 of frames 1 and 10
    assert main(["plot", str(out), "-o", str(gif), "--person", "1"]) == EXIT_OK
    with Image.open(gif) as image:
        assert image.n_frames == 1


@pytest.mark.skipif(shutil.which("ffmpeg") is not None, reason="ffmpeg is installed: .mp4 works")
def test_plot_to_mp4_without_ffmpeg_says_so(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out.json"
    assert main(["lift", str(_openpose_folder(tmp_path)), "--local", "-o", str(out)]) == EXIT_OK
    assert main(["plot", str(out), "-o", str(tmp_path / "walk.mp4")]) == EXIT_USAGE
    assert "needs ffmpeg" in capsys.readouterr().err and not (tmp_path / "walk.mp4").exists()


def test_an_empty_folder_is_a_usage_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["lift", str(tmp_path), "--local"]) == EXIT_USAGE
    assert "no .json or .txt files" in capsys.readouterr().err


# ---- sequences: the temporal mode, the frame rate, tracks, clips cut into requests ----


def _walkers(tmp_path: Path, frames: int = 200) -> Path:
    """An OpenPose folder: person A walks the whole clip; person B, further right, is not found in 10
    frames (a gap the service bridges); the detector lists them in either order."""
    folder = tmp_path / "walk"
    folder.mkdir()
    rng = np.random.default_rng(3)
    for f in range(frames):
        a = _body25(1.5 * f) + rng.normal(0, 2.0, (25, 2))
        b = _body25(700.0 - 1.0 * f) + rng.normal(0, 2.0, (25, 2))
        people = [a] if 80 <= f < 90 else ([b, a] if f % 4 == 1 else [a, b])
        _openpose_frame(folder / f"walk_{f:012d}_keypoints.json", people)
    return folder


def _lifted(args: list[str]) -> dict[str, Any]:
    out = Path(args[args.index("-o") + 1])
    assert main(args) == EXIT_OK
    return dict(json.loads(out.read_text()))


def _by_person(data: dict[str, Any]) -> dict[str, list[dict[str, Any]]]:
    """The output's poses by track, each track named by where its person starts (left or right)."""
    tracks: dict[str, list[dict[str, Any]]] = {}
    for pose in data["poses"]:
        tracks.setdefault(pose["track_id"], []).append(pose)
    return {("A" if poses[0]["input"]["keypoints"][8][0] < 700 else "B"): poses for poses in tracks.values()}


def test_a_sequence_is_lifted_temporally_by_default_and_one_frame_alone(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = _lifted(["lift", str(_h36m_npz(tmp_path, 30)), "--local", "-o", str(tmp_path / "seq.json")])
    err = capsys.readouterr().err
    assert data["temporal"] in ("offline", "causal") and data["fps"] == 30.0
    assert "assuming 30 fps" in err
    if data["temporal"] == "causal":  # until the offline model ships
        assert "no offline temporal model here: lifting the sequence with temporal causal" in err
    assert all(p["temporal"] and p["track_id"] == "0" for p in data["poses"])
    one = tmp_path / "one.json"
    one.write_text(json.dumps(POSE_2D.tolist()))
    single = _lifted(["lift", str(one), "--local", "-o", str(tmp_path / "single.json")])
    assert single["temporal"] == "off" and single["fps"] is None
    assert single["poses"][0]["track_id"] is None and not single["poses"][0]["temporal"]
    assert "assuming" not in capsys.readouterr().err


def test_the_files_frame_rate_and_tracks_are_used(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "poses.npz"
    np.savez(path, keypoints=np.stack([project(POSE_3D, 2.0 * i) for i in range(12)]), fps=np.array(25.0))
    data = _lifted(["lift", str(path), "--local", "--temporal", "causal", "-o", str(tmp_path / "a.json")])
    assert data["fps"] == 25.0 and "assuming" not in capsys.readouterr().err
    body = {"format": "h36m17", "fps": 50, "poses": [
        {"keypoints": project(POSE_3D, 2.0 * f).tolist(), "track_id": t, "frame": f}
        for f in range(6) for t in ("x", "y")]}  # fmt: skip
    path = tmp_path / "body.json"
    path.write_text(json.dumps(body))
    data = _lifted(["lift", str(path), "--local", "--temporal", "causal", "-o", str(tmp_path / "b.json")])
    assert data["fps"] == 50.0 and [p["track_id"] for p in data["poses"]] == ["x", "y"] * 6
    assert [p["frame"] for p in data["poses"]] == [f for f in range(6) for _ in "xy"]
    with pytest.raises(SystemExit) as info:
        main(["lift", str(path), "--local", "--fps", "0"])
    assert info.value.code == EXIT_USAGE
    assert "--fps: expected frames per second in (0, 240]" in capsys.readouterr().err


def test_without_temporal_models_a_sequence_falls_back_and_an_asked_mode_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(local, "TEMPORAL_MODELS", {})
    npz = _h36m_npz(tmp_path, 5)
    data = _lifted(["lift", str(npz), "--local", "-o", str(tmp_path / "out.json")])
    assert data["temporal"] == "off" and not any(p["temporal"] for p in data["poses"])
    assert "lifting the sequence with temporal off" in capsys.readouterr().err
    assert main(["lift", str(npz), "--local", "--temporal", "causal"]) == EXIT_REJECTED
    assert "no causal temporal model is loaded" in capsys.readouterr().err


@pytest.mark.parametrize("mode", TEMPORAL_MODES)
def test_the_windowed_cli_equals_one_request(
    tmp_path: Path,
    live_service: LiveService,
    small_service: LiveService,
    monkeypatch: pytest.MonkeyPatch,
    mode: str,
) -> None:
    """A 200-frame clip of two people, cut into requests of 120 poses (the service's and --local's
    REPNET_MAX_TEMPORAL_POSES), answers as one request: through the service and in this process."""
    folder = str(_walkers(tmp_path))
    base = ["lift", folder, "--temporal", mode, "--fps", "30", "-o"]
    one = _lifted([*base, str(tmp_path / "one.json"), "--url", live_service.http_url])
    cut = _lifted([*base, str(tmp_path / "cut.json"), "--url", small_service.http_url])
    local_one = _lifted([*base, str(tmp_path / "local_one.json"), "--local"])
    monkeypatch.setenv("REPNET_MAX_TEMPORAL_POSES", str(SMALL_TEMPORAL_POSES))
    local_cut = _lifted([*base, str(tmp_path / "local_cut.json"), "--local"])
    tracks = _by_person(one)
    assert len({p["track_id"] for p in one["poses"]}) == 2  # B keeps its track over its gap
    assert sorted(tracks) == ["A", "B"] and len(tracks["A"]) == 200 and len(tracks["B"]) == 190
    for data in (cut, local_one, local_cut):
        assert [p["track_id"] for p in data["poses"]] == [p["track_id"] for p in one["poses"]]
        got = _by_person(data)
        for person in ("A", "B"):
            want = np.array([p["pose_3d_camera"] for p in tracks[person]])
            have = np.array([p["pose_3d_camera"] for p in got[person]])
            np.testing.assert_allclose(_directions(have), _directions(want), atol=2e-4)  # the same windows
            np.testing.assert_allclose(have, want, atol=3.0)  # bone lengths: the mean over a part


def _directions(poses: np.ndarray) -> np.ndarray:
    bones = poses[:, 1:] - poses[:, list(MODEL_PARENTS[1:])]
    return np.asarray(bones / np.linalg.norm(bones, axis=-1, keepdims=True))


def test_coco_results_are_read_by_image_with_every_person_tracked(tmp_path: Path) -> None:
    results = []
    for image in (7, 8, 9):
        for shift in (0.0, 600.0) if image != 8 else (600.0, 0.0):
            points, found = from_model_joints(FORMATS["coco17"], (POSE_2D + [shift + image, 0.0])[None])
            triples = np.concatenate(
                [np.nan_to_num(points[0]), np.where(found[0], 0.8, 0.0)[:, None]], axis=1
            )
            results.append(
                {"image_id": image, "category_id": 1, "keypoints": triples.ravel().tolist(), "score": 0.9}
            )
    path = tmp_path / "results.json"
    path.write_text(json.dumps(list(reversed(results))))
    poses = load_poses(path)
    assert poses.format == "coco17" and poses.frame.tolist() == [7, 7, 8, 8, 9, 9]
    assert poses.person.tolist() == [0, 1] * 3 and poses.confidence is not None
    data = _lifted(["lift", str(path), "--local", "--temporal", "causal", "-o", str(tmp_path / "out.json")])
    left = [p["track_id"] for p in data["poses"] if p["input"]["keypoints"][11][0] < 600]
    right = [p["track_id"] for p in data["poses"] if p["input"]["keypoints"][11][0] > 600]
    assert len(set(left)) == len(set(right)) == 1 and left[0] != right[0]


def _coco_images(tmp_path: Path, ids: list[int]) -> Path:
    """COCO annotations of three people in each image `ids`."""
    annotations = []
    for k, image in enumerate(ids):
        for person, shift in enumerate((0.0, 600.0, 1200.0)):
            points, found = from_model_joints(FORMATS["coco17"], (POSE_2D + [shift + k, 0.0])[None])
            flags = np.where(found[0], 2.0, 0.0)[:, None]
            triples = np.concatenate([np.nan_to_num(points[0]), flags], axis=1).ravel().tolist()
            annotations.append({"id": 10 * k + person, "image_id": image, "keypoints": triples})
    path = tmp_path / f"coco_{len(ids)}.json"
    path.write_text(json.dumps({"images": [{"id": i} for i in ids], "annotations": annotations}))
    return path


def test_unrelated_coco_images_are_lifted_one_by_one_and_numbered_ones_as_a_clip(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    stills = _coco_images(tmp_path, [397133, 37777, 252219, 87038])
    data = _lifted(["lift", str(stills), "--local", "-o", str(tmp_path / "stills.json")])
    err = capsys.readouterr().err
    said = "4 still images (image ids not consecutive): lifted one by one; --fps N to treat them as a video"
    assert said in err
    assert "assuming" not in err and "fps" not in err.replace("--fps N", "")
    assert data["temporal"] == "off" and data["fps"] is None and data["stills"] == "image ids not consecutive"
    assert len(data["poses"]) == 12
    assert all(p["track_id"] is None and not p["temporal"] for p in data["poses"])

    video = _lifted(["lift", str(stills), "--local", "--fps", "25", "-o", str(tmp_path / "video.json")])
    assert "still images" not in capsys.readouterr().err  # a frame rate makes them a video
    assert video["temporal"] != "off" and video["fps"] == 25.0 and video["stills"] is None

    clip = _coco_images(tmp_path, [1000, 1001, 1002, 1004, 1005])  # 1003: nobody found
    data = _lifted(["lift", str(clip), "--local", "-o", str(tmp_path / "clip.json")])
    err = capsys.readouterr().err
    assert "still images" not in err and "5 frames (image ids in sequence): assuming 30 fps" in err
    assert data["temporal"] != "off" and data["fps"] == 30.0 and data["stills"] is None
    assert len({p["track_id"] for p in data["poses"]}) == 3


@pytest.mark.parametrize(
    ("numbered_by", "frames", "reason"),
    [
        ("image ids", [397133, 37777, 252219, 397133], "image ids not consecutive"),
        ("image ids", [5, 9], "image ids not consecutive"),
        ("image ids", [5, 6], None),
        ("image ids", [0, 1, 2, 10, 11], None),  # most follow one another
        ("image ids", [0, 2, 4, 6], "image ids not consecutive"),
        ("file names", [3, 40, 41, 90], "file names not consecutive"),
        ("image names", [0, 1, 2], "image ids not numbered"),
        (None, [397133, 37777], None),  # the order in the file: a clip
        ("image ids", [397133, 397133], None),  # one image
    ],
)
def test_stills_reason_reads_the_numbering(
    numbered_by: str | None, frames: list[int], reason: str | None
) -> None:
    assert stills_reason(numbered_by, frames) == reason


def test_plot_animates_one_track_of_a_crowded_sequence(tmp_path: Path) -> None:
    folder, out, gif = tmp_path / "crowd", tmp_path / "out.json", tmp_path / "b.gif"
    folder.mkdir()
    for f in range(6):  # B is listed first in odd frames, and missing in frame 4
        a, b = _body25(3.0 * f), _body25(700.0 - 3.0 * f)
        people = [a] if f == 4 else ([b, a] if f % 2 else [a, b])
        _openpose_frame(folder / f"crowd_{f:012d}_keypoints.json", people)
    data = _lifted(["lift", str(folder), "--local", "--temporal", "causal", "-o", str(out)])
    b_track = data["poses"][1]["track_id"]  # frame 0: A, then B
    assert [p["frame"] for p in data["poses"] if p["track_id"] == b_track] == [0, 1, 2, 3, 5]
    assert main(["plot", str(out), "-o", str(gif), "--track", b_track]) == EXIT_OK
    from PIL import Image

    with Image.open(gif) as image:
        assert image.n_frames == 5
    person_1 = [p["track_id"] for p in data["poses"] if p["person"] == 1]
    assert len(set(person_1)) == 2  # the detector's index 1 is A in some frames and B in others
    assert main(["plot", str(out), "-o", str(gif), "--track", "nobody"]) == EXIT_USAGE


def test_coco_results_with_format_coco17_are_lifted(tmp_path: Path) -> None:
    path, out_path = _coco_file(tmp_path), tmp_path / "out.json"
    assert main(["lift", str(path), "--format", "coco17", "--local", "-o", str(out_path)]) == EXIT_OK
    out = json.loads((tmp_path / "out.json").read_text())
    assert out["format"] == "coco17" and len(out["poses"]) == 3


def test_an_input_value_in_an_error_is_cut_short_with_a_hint(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "odd.json"
    path.write_text(json.dumps({"keypoints": [[{"image_id": 1, "values": list(range(400))}] * 17]}))
    assert main(["lift", str(path), "--local"]) == EXIT_USAGE
    err = capsys.readouterr().err
    quoted = err.split("got ", 1)[1].split("; each joint")[0]
    assert len(quoted) < 130 and "characters)" in quoted
    assert "each joint is [x, y] or [x, y, confidence]" in err and "--image-size" in err


def test_mediapipe_rows_need_an_image_size_and_lift_with_the_flag_as_with_the_bodys(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    landmarks, found = from_model_joints(FORMATS["mediapipe33"], project(POSE_3D, 20.0)[None])
    pixels = np.where(found[0][:, None], landmarks[0], landmarks[0, 0])  # (33, 2) px; the face at the nose
    rows = [[x / 1280, y / 720, 0.0, 0.8] for x, y in pixels.tolist()]
    bare, body = tmp_path / "bare.json", tmp_path / "body.json"
    bare.write_text(json.dumps({"poses": [{"keypoints": rows}], "format": "mediapipe33"}))
    sized = {"poses": [{"keypoints": rows}], "format": "mediapipe33", "image_size": [1280, 720]}
    body.write_text(json.dumps(sized))
    assert main(["lift", str(bare), "--local"]) == EXIT_USAGE
    assert "give the image size with --image-size W H" in capsys.readouterr().err
    answers = []
    np.savez(npz := tmp_path / "landmarks.npz", keypoints=np.array([rows]), format=np.array("mediapipe33"))
    sized_flag = ["--image-size", "1280", "720"]
    for args in ([str(bare), *sized_flag], [str(body)], [str(npz), *sized_flag]):
        assert main(["lift", *args, "--local", "-o", str(tmp_path / "out.json"), "--overwrite"]) == EXIT_OK
        answers.append(json.loads((tmp_path / "out.json").read_text())["poses"][0])
    assert answers[0]["reprojection"] == answers[1]["reprojection"] == answers[2]["reprojection"]
    np.testing.assert_allclose(answers[0]["input"]["keypoints"][11], pixels[11], atol=1e-6)  # left shoulder
    assert answers[0]["input"]["confidence"][11] == 0.8


def test_a_format_alias_and_a_joint_count_are_answered_with_the_format_they_mean(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit):
        main(["lift", "x.json", "--format", "openpose"])
    assert "for OpenPose BODY_25 use --format body25" in capsys.readouterr().err
    body, _ = from_model_joints(FORMATS["body25"], POSE_2D[None])
    path = tmp_path / "body.json"
    path.write_text(json.dumps([[None if np.isnan(p).any() else p.tolist() for p in body[0]]]))
    assert main(["lift", str(path), "--local"]) == EXIT_USAGE
    err = capsys.readouterr().err
    assert "25 joints: this looks like body25 (OpenPose BODY_25) or body25b (OpenPose BODY_25B" in err
    assert "use --format body25 or --format body25b" in err


@pytest.mark.parametrize(
    ("content", "said"),
    [
        ("", "the file is empty"),
        ("  \n", "the file is empty"),
        ('{"a": ', "not valid JSON: Expecting value"),
        ('[{"image_id": 1, "bbox": [1, 2, 3, 4], "score": 0.9}]', "boxes and no keypoints"),
        ('{"annotations": [{"image_id": 1, "bbox": [1, 2, 3, 4], "num_keypoints": 0}]}', "boxes only"),
    ],
)
def test_an_empty_broken_or_boxes_only_file_is_named_for_what_it_is(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], content: str, said: str
) -> None:
    """Issue 31: an empty file said `Expecting value: line 1 column 1`, a boxes-only COCO file
    `expected a joint, got {'bbox': ...}`."""
    path = tmp_path / "input.json"
    path.write_text(content)
    assert main(["lift", str(path), "--local", "--format", "coco17"]) == EXIT_USAGE
    err = capsys.readouterr().err
    assert f"{path}: " in err and said in err and "Traceback" not in err


def coco_annotations(tmp_path: Path, people: int = 3, empty: tuple[int, ...] = (1,)) -> Path:
    """A COCO annotation file of one image: `people` people, those at `empty` with no keypoint
    (`num_keypoints: 0`, as every COCO annotation file has)."""
    points, _ = from_model_joints(FORMATS["coco17"], project(POSE_3D)[None])
    full = [
        v
        for x, y in points[0].tolist()
        for v in ((0, 0, 0) if np.isnan(x) else (round(x, 1), round(y, 1), 2))
    ]
    annotations = [
        {"id": 100 + k, "image_id": 397133, "num_keypoints": 0 if k in empty else 15, "bbox": [1, 2, 3, 4],
         "keypoints": [0] * 51 if k in empty else full}
        for k in range(people)
    ]  # fmt: skip
    path = tmp_path / "person_keypoints.json"
    path.write_text(json.dumps({"images": [{"id": 397133}], "annotations": annotations}))
    return path


@pytest.mark.parametrize("where", ["local", "remote"])
def test_a_file_with_unusable_poses_lifts_the_others_and_names_the_skipped_ones(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], live_service: LiveService, where: str
) -> None:
    """Issue 31: a COCO annotation file's person of num_keypoints 0 refused the whole file, named as
    poses[1] of the flattened file. Now the others are lifted and the skipped one is named by its
    image and annotation ids, on stderr and in the output."""
    path, out = coco_annotations(tmp_path), tmp_path / "out.json"
    backend = ["--local"] if where == "local" else ["--url", live_service.http_url]
    assert main(["lift", str(path), "--format", "coco17", *backend, "-o", str(out)]) == EXIT_OK
    err = capsys.readouterr().err
    assert (
        "skipped 1 of 3 poses" in err
        and "frame 397133, person 1 (image_id 397133, id 101): keypoints: 0 of" in err
    )
    document = json.loads(out.read_text())
    assert [(p["frame"], p["person"]) for p in document["poses"]] == [(397133, 0), (397133, 2)]
    assert document["skipped"] == [
        {"frame": 397133, "person": 1, "source": "image_id 397133, id 101",
         "errors": [{"field": "keypoints", "code": "too_few_visible",
                     "reason": document["skipped"][0]["errors"][0]["reason"]}]}
    ]  # fmt: skip


def test_strict_refuses_the_file_and_a_file_of_no_usable_pose_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path, out = coco_annotations(tmp_path), tmp_path / "out.json"
    assert (
        main(["lift", str(path), "--format", "coco17", "--local", "--strict", "-o", str(out)])
        == EXIT_REJECTED
    )
    assert "1 of 3 poses break the input rules (without --strict they are skipped)" in capsys.readouterr().err
    assert not out.exists()
    path = coco_annotations(tmp_path, people=2, empty=(0, 1))
    assert main(["lift", str(path), "--format", "coco17", "--local", "-o", str(out)]) == EXIT_REJECTED
    assert "none of the 2 poses can be lifted" in capsys.readouterr().err
    assert not out.exists()
