"""`repnet lift -o`: the writer chosen by the suffix (.json, .npz, .csv, .bvh), and the BVH read back."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from repnet.cli.main import EXIT_OK, EXIT_USAGE, main
from repnet.core.formats import FORMATS, MODEL_JOINTS, MODEL_PARENTS, from_model_joints, to_model_joints
from repnet.io import bvh
from repnet.io.output import CAMERA_TO_BVH, CSV_HEADER
from tests.conftest import CENTRE_PX, FOCAL_PX, POSE_3D, project

INTRINSICS = f"{FOCAL_PX},{FOCAL_PX},{CENTRE_PX[0]},{CENTRE_PX[1]}"


def _clip(tmp_path: Path, tracks: tuple[str, ...] = ("a",), frames: int = 8) -> Path:
    """A POST /lift body of `frames` frames per track: the test pose turning and walking sideways."""
    poses = []
    for k, track in enumerate(tracks):
        for t in range(frames):
            points = project(POSE_3D, yaw_deg=10.0 + 3 * t, distance_mm=4500.0 + 800 * k) + [
                6.0 * t - 200 * k,
                0,
            ]
            poses.append({"keypoints": points.tolist(), "track_id": track, "frame": t})
    path = tmp_path / "clip.json"
    path.write_text(json.dumps({"poses": poses, "fps": 25}))
    return path


def _lift(clip: Path, out: Path, *flags: str) -> None:
    assert main(["lift", str(clip), "--local", "--intrinsics", INTRINSICS, *flags, "-o", str(out)]) == EXIT_OK


def _motion_positions(path: Path) -> tuple[bvh.Motion, np.ndarray]:
    """The parsed BVH and its forward kinematics in the model's joint order, metres (BVH axes)."""
    motion = bvh.parse_bvh(path.read_text())
    order = [motion.names.index(name) for name in MODEL_JOINTS]
    return motion, bvh.forward_kinematics(motion)[:, order]


def test_bvh_round_trip_of_a_rigid_clip_is_exact_to_a_micrometre() -> None:
    """Positions made by forward kinematics of a skeleton (constant bones, rigid hips and shoulders):
    the solved rotations, written and parsed back, give them again."""
    rng = np.random.default_rng(3)
    base = rng.normal(0, 0.2, (17, 3))
    offsets = np.array([base[j] - base[p] if p >= 0 else np.zeros(3) for j, p in enumerate(MODEL_PARENTS)])
    source = bvh.Motion(MODEL_JOINTS, MODEL_PARENTS, offsets, rng.normal(0, 1, (30, 3)),
                        rng.normal(0, 40, (30, 17, 3)), 0.04)  # fmt: skip
    positions = bvh.forward_kinematics(source)
    text = bvh.write_bvh(bvh.solve_motion(positions, 0.04))
    assert (
        text.startswith("HIERARCHY\nROOT pelvis\n") and "\nMOTION\nFrames: 30\nFrame Time: 0.040000\n" in text
    )
    assert text.count("End Site") == 5  # ankles, wrists, head
    motion = bvh.parse_bvh(text)
    fk = bvh.forward_kinematics(motion)[:, [motion.names.index(n) for n in MODEL_JOINTS]]
    assert np.abs(fk - positions).max() < 1e-5  # m: 10 µm


def test_euler_angles_give_back_their_rotation() -> None:
    angles = np.random.default_rng(0).uniform(-170, 170, (50, 3))
    angles[:, 1] /= 2  # X within (-90, 90), where Z X Y angles are unique
    again = np.array([bvh.to_euler(r) for r in bvh.from_euler(angles)])
    np.testing.assert_allclose(again, angles, atol=1e-9)


def test_lift_to_bvh_follows_the_lifted_positions_and_the_root(tmp_path: Path) -> None:
    clip = _clip(tmp_path)
    _lift(clip, tmp_path / "clip.bvh", "--person-height", "1.7")
    _lift(clip, tmp_path / "clip.npz", "--person-height", "1.7")
    motion, fk = _motion_positions(tmp_path / "clip.bvh")
    lifted = np.load(tmp_path / "clip.npz")
    placed = (lifted["pose_3d_camera"] / 1000.0 + lifted["root_camera_m"][:, None]) @ CAMERA_TO_BVH.T
    assert motion.frame_time == pytest.approx(1 / 25)
    # a BVH skeleton is rigid: the answers' hips and shoulders change shape a little from frame to
    # frame (the temporal model fixes bone lengths, not the angles between sibling bones)
    error = np.linalg.norm(fk - placed, axis=-1)  # (T, 17) m
    assert error.mean() < 1e-3 and error.max() < 5e-3 and error[:, 0].max() < 1e-5
    assert np.ptp(motion.root_position[:, 0]) > 0.05  # the root walks to the side
    assert (motion.root_position[:, 2] < -3).all()  # in front of the camera: -z in BVH's Y-up frame


def test_one_bvh_per_track_with_the_root_at_the_origin_without_intrinsics(tmp_path: Path) -> None:
    clip = _clip(tmp_path, tracks=("a", "b"), frames=5)
    assert main(["lift", str(clip), "--local", "-o", str(tmp_path / "out.bvh")]) == EXIT_OK
    written = sorted(p.name for p in tmp_path.glob("out*.bvh"))
    assert written == ["out.track-a.bvh", "out.track-b.bvh"]
    motion, _ = _motion_positions(tmp_path / "out.track-b.bvh")
    assert len(motion.rotations) == 5 and np.abs(motion.root_position).max() == 0.0


def test_csv_has_a_row_per_pose_per_joint_with_the_reply(tmp_path: Path) -> None:
    clip = _clip(tmp_path, frames=3)
    _lift(clip, tmp_path / "out.csv")
    _lift(clip, tmp_path / "out.json")
    rows = list(csv.DictReader((tmp_path / "out.csv").open()))
    assert tuple(rows[0]) == CSV_HEADER and len(rows) == 3 * 17
    poses = json.loads((tmp_path / "out.json").read_text())["poses"]
    row = rows[17 + 5]  # frame 1, joint 5
    assert (row["frame"], row["track_id"], row["joint"]) == ("1", "a", MODEL_JOINTS[5])
    pose = [float(row[k]) for k in ("x_mm", "y_mm", "z_mm")]
    np.testing.assert_allclose(pose, poses[1]["pose_3d_camera"][5], atol=0.01)
    camera = np.array(poses[1]["root_camera_m"]) + np.array(poses[1]["pose_3d_camera"][5]) / 1000
    np.testing.assert_allclose([float(row[k]) for k in ("x_camera_m", "y_camera_m", "z_camera_m")], camera,
                               atol=1e-5)  # fmt: skip


def test_npz_holds_every_reply_field_and_lifts_again(tmp_path: Path) -> None:
    clip = _clip(tmp_path, frames=4)
    _lift(clip, tmp_path / "out.npz")
    lifted = np.load(tmp_path / "out.npz")
    assert lifted["pose_3d"].shape == (4, 17, 3) and lifted["root_camera_m"].shape == (4, 3)
    assert (
        lifted["root_height_source"].tolist() == ["template"] * 4 and lifted["track_id"].tolist() == ["a"] * 4
    )
    assert lifted["joints"].tolist() == list(MODEL_JOINTS) and float(lifted["fps"]) == 25.0
    again = tmp_path / "again.json"
    assert (
        main(["lift", str(tmp_path / "out.npz"), "--local", "--temporal", "off", "-o", str(again)]) == EXIT_OK
    )
    poses = json.loads(again.read_text())["poses"]
    np.testing.assert_allclose([p["input"]["keypoints"] for p in poses], lifted["keypoints"])


def test_an_unknown_suffix_is_refused_before_lifting(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out.txt"
    assert main(["lift", str(tmp_path / "absent.json"), "--local", "-o", str(out)]) == EXIT_USAGE
    err = capsys.readouterr().err
    assert "unknown output suffix '.txt'" in err and ".json, .npz, .csv, .bvh" in err and not out.exists()


def test_a_missing_folder_or_an_existing_output_is_refused_before_lifting(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    clip = _clip(tmp_path, frames=3)
    missing = tmp_path / "no such folder" / "out.json"
    assert main(["lift", str(clip), "--local", "-o", str(missing)]) == EXIT_USAGE
    assert "does not exist" in capsys.readouterr().err
    out = tmp_path / "out.json"
    out.write_text("an earlier lift")
    assert main(["lift", str(clip), "--local", "-o", str(out)]) == EXIT_USAGE
    assert "--overwrite" in capsys.readouterr().err and out.read_text() == "an earlier lift"
    assert main(["lift", str(clip), "--local", "-o", str(out), "--overwrite"]) == EXIT_OK
    assert json.loads(out.read_text())["poses"]
    (tmp_path / "anim.track-a.bvh").write_text("kept")  # a per-person file an earlier .bvh lift wrote
    assert main(["lift", str(clip), "--local", "-o", str(tmp_path / "anim.bvh")]) == EXIT_USAGE
    assert "anim.track-a.bvh exists" in capsys.readouterr().err


def test_hostile_track_ids_make_safe_distinct_file_names(tmp_path: Path) -> None:
    tracks = ("../up", "a\x00b", "a/b", "a_b", "x" * 128)
    clip = _clip(tmp_path, tracks=tracks, frames=3)
    (tmp_path / "out").mkdir()
    assert main(["lift", str(clip), "--local", "-o", str(tmp_path / "out" / "m.bvh")]) == EXIT_OK
    written = sorted(p.name for p in (tmp_path / "out").iterdir())
    assert len(written) == len(tracks) and all(name.startswith("m.track-") for name in written), written
    assert "m.track-a_b.bvh" in written  # a safe id is kept as it is; "a/b" gets a hash beside it
    assert sorted(p.name for p in tmp_path.iterdir()) == ["clip.json", "out"]  # nothing escaped


def test_readme_export_snippet_runs_as_written(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Each `repnet` line of docs/API.md's export block, run in a folder holding a tracked clip.json."""
    import shlex

    readme = (Path(__file__).resolve().parents[2] / "docs" / "API.md").read_text()
    block = (
        readme.split("### Where the person stands, and export", 1)[1].split("```bash\n", 1)[1].split("```")[0]
    )
    lines = [shlex.split(line, comments=True) for line in block.splitlines() if line.startswith("repnet ")]
    assert len(lines) == 5
    monkeypatch.chdir(tmp_path)
    _clip(tmp_path, frames=6)
    for argv in lines:
        assert main(argv[1:]) == EXIT_OK, argv
    for name in ("out.json", "clip.bvh", "clip.csv", "clip.npz", "walk.gif"):
        assert (tmp_path / name).stat().st_size > 0, name
    assert all(
        p["root_height_source"] == "given" for p in json.loads((tmp_path / "out.json").read_text())["poses"]
    )


def test_a_frame_without_the_person_repeats_the_pose_before_it() -> None:
    from repnet.client.result import LiftResult
    from repnet.io.output import person_positions

    def result(shift: float) -> LiftResult:
        pose = np.asarray(POSE_3D, np.float32) + [shift, 0.0, 0.0]
        flags, eye = np.zeros(17, bool), np.eye(3, dtype=np.float32)
        flat = np.zeros((17, 2), np.float32)
        return LiftResult(pose, pose, eye[:2], 1.0, eye, flat, 0.0, flags, flags, flags, MODEL_JOINTS, "m")

    positions = person_positions([result(0.0), result(100.0), result(300.0)], np.array([4, 5, 7]))
    assert positions.shape == (4, 17, 3)  # frames 4 to 7
    np.testing.assert_allclose(positions[2], positions[1])  # frame 6 missing: frame 5's pose
    np.testing.assert_allclose(positions[3, :, 0] - positions[0, :, 0], 0.3)  # m, x kept in BVH axes


@pytest.mark.parametrize("fmt", ["h36m17", "coco17", "mpii16", "body25"])
def test_csv_input_points_are_the_files_points_at_the_model_joints(tmp_path: Path, fmt: str) -> None:
    """Issue 31: the CSV wrote input joint j in model joint j's row (coco17's nose as the pelvis), and
    nothing for body25. Now each row has the file's point mapped to that model joint (a derived
    joint, coco17's pelvis, the midpoint of its sources); the joints the model lacks (eyes, ears)
    get points no model joint has, so a wrong mapping shows."""
    table = FORMATS[fmt]
    pose = project(POSE_3D)  # (17, 2) px
    points, present = from_model_joints(table, pose[None])
    points = np.where(present[..., None], points, 1000.0 + np.arange(len(table.joint_names))[None, :, None])
    path = tmp_path / "pose.json"
    path.write_text(json.dumps(points[0].round(2).tolist()))
    _lift(path, tmp_path / "out.csv", "--format", fmt)
    rows = list(csv.DictReader((tmp_path / "out.csv").open()))
    expected, visible, derived, _ = to_model_joints(table, points.round(2), np.ones(points.shape[:2], bool))
    for j, row in enumerate(rows):
        assert row["joint"] == MODEL_JOINTS[j]
        if visible[0, j]:
            np.testing.assert_allclose(
                [float(row["input_x_px"]), float(row["input_y_px"])], expected[0, j], atol=0.01
            )
            if not derived[0, j]:  # one source: the model joint's own point
                np.testing.assert_allclose(expected[0, j], pose[j], atol=0.02)
        else:
            assert (row["input_x_px"], row["input_y_px"]) == ("", "")


def test_a_non_finite_point_of_confidence_0_is_a_missing_joint_in_every_output(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Issue 31: `Infinity` in a file crashed the CLI writing its JSON (the input echoed), while HTTP
    reads the same joint as missing when its confidence is 0. Now it is null in the echo."""
    rows = [[float(x), float(y), 1.0] for x, y in project(POSE_3D)]
    rows[3] = [float("inf"), 5.0, 0.0]
    path = tmp_path / "pose.json"
    path.write_text(json.dumps(rows))  # Python writes Infinity
    for name in ("out.json", "out.csv", "out.npz"):
        _lift(path, tmp_path / name)
    pose = json.loads((tmp_path / "out.json").read_text())["poses"][0]
    assert pose["input"]["keypoints"][3] is None and pose["input"]["confidence"][3] is None
    assert not pose["visible"][3]
    rows[3][2] = 0.9  # seen: refused by name, no traceback
    path.write_text(json.dumps(rows))
    assert main(["lift", str(path), "--local", "-o", str(tmp_path / "again.json")]) != EXIT_OK
    err = capsys.readouterr().err
    assert "frame 0, person 0: keypoints[3] (right_ankle): coordinates must be finite numbers" in err
    assert "Traceback" not in err and not (tmp_path / "again.json").exists()


def test_a_device_takes_the_json_and_one_pose_is_counted_as_one(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "pose.json"
    path.write_text(json.dumps(project(POSE_3D).tolist()))
    assert main(["lift", str(path), "--local", "-o", "/dev/null"]) == EXIT_OK
    assert "lifted 1 pose of 1 frame (h36m17" in capsys.readouterr().err
