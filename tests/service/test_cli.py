"""End-to-end tests of the `repnet` command: lift files locally and via the service, plot, formats."""

from __future__ import annotations

import json
import socket
from pathlib import Path

import numpy as np
import pytest

from service.cli import EXIT_OK, EXIT_REJECTED, EXIT_UNREACHABLE, EXIT_USAGE, load_poses, main
from service.formats import FORMATS, MODEL_JOINTS, from_model_joints
from tests.conftest import POSE_2D, POSE_3D, LiveService, project


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


def test_lift_to_stdout(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "one.json"
    path.write_text(json.dumps(POSE_2D.tolist()))
    assert main(["lift", str(path), "--local"]) == EXIT_OK
    assert len(json.loads(capsys.readouterr().out)["poses"]) == 1


def test_rejected_pose_is_named_by_its_index_in_the_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    keypoints = np.stack([POSE_2D] * 5)
    keypoints[3] = 100.0  # every joint at one point
    path = tmp_path / "bad.npz"
    np.savez(path, keypoints=keypoints)
    assert main(["lift", str(path), "--local", "--batch-size", "2"]) == EXIT_REJECTED
    err = capsys.readouterr().err
    assert "poses[3].keypoints" in err and "one point" in err


def test_openpose_json_is_read_as_body25(tmp_path: Path) -> None:
    points, visible = from_model_joints(FORMATS["body25"], POSE_2D[None])
    flat = np.concatenate([np.nan_to_num(points[0]), visible[0, :, None].astype(float)], axis=1).ravel()
    path = tmp_path / "frame_000000_keypoints.json"
    path.write_text(json.dumps({"version": 1.3, "people": [{"pose_keypoints_2d": flat.tolist()}]}))
    poses = load_poses(path)
    assert poses.format == "body25" and poses.points.shape == (1, 25, 2)
    assert np.isnan(poses.points[0, FORMATS["body25"].joint_names.index("left_ear")]).all()
    assert main(["lift", str(path), "--local", "-o", str(tmp_path / "out.json")]) == EXIT_OK


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
        (json.dumps(POSE_2D.tolist()), ["--model", "x.onnx"], "--model needs --local"),
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
