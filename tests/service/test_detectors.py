"""repnet.io.detectors and repnet.io.coco: each detector's file (tests/fixtures/detectors/) read as its
tool writes it, to the poses, format, frames, people and labels it holds; broken variants refused
by an InputFileError naming the file and the field."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from repnet.core.format_hints import raw_output_hint
from repnet.io.pose_file import read_input
from repnet.io.poses import InputFileError, Poses
from tests.service.detector_files import BUILDERS, FIXTURES, IMAGE_SIZE, Expected, write_fixtures

# The file (or folder) of each fixture that repnet lift is given.
READ = {"mmpose video": "mmpose_video.json", "mmpose image": "mmpose_image.json",
        "yolo summary": "yolo_summary.json", "yolo labels": "yolo_labels",
        "mediapipe results": "mediapipe_python.json", "alphapose": "alphapose-results.json",
        "coco wholebody": "coco_wholebody.json", "openpose coco18": "openpose_coco18_*.json"}  # fmt: skip


def read(spec: str, size: tuple[float, float] | None = None) -> Poses:
    return read_input(spec, lambda files: files, size)


def assert_read_as(poses: Poses, want: Expected) -> None:
    np.testing.assert_allclose(poses.points, want.points, rtol=1e-12, atol=1e-9)
    if want.confidence is None:
        assert poses.confidence is None
    else:
        assert poses.confidence is not None
        np.testing.assert_allclose(poses.confidence, want.confidence)
    assert (poses.format, poses.frame.tolist(), poses.person.tolist()) == (
        want.format,
        want.frame,
        want.person,
    )
    assert list(poses.label or ()) == want.label


def test_the_fixtures_are_what_the_generator_writes(tmp_path: Path) -> None:
    write_fixtures(tmp_path)
    made = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*") if p.is_file())
    kept = sorted(
        p.relative_to(FIXTURES) for p in FIXTURES.rglob("*") if p.is_file() and p.name != "README.md"
    )
    assert made == kept
    for name in made:
        assert (tmp_path / name).read_text() == (FIXTURES / name).read_text(), name


@pytest.mark.parametrize("name", [n for n in BUILDERS if n != "openpose coco18"])
def test_each_detector_file_is_read_as_its_tool_writes_it(name: str) -> None:
    want = BUILDERS[name]()
    assert_read_as(read(str(FIXTURES / READ[name]), want.image_size), want)


def test_openpose_coco18_frames_read_as_coco18() -> None:
    """OpenPose's COCO model writes 18 joints per person (item 5 of issue 31)."""
    want = BUILDERS["openpose coco18"]()
    assert_read_as(read(str(FIXTURES / READ["openpose coco18"])), want)


def test_the_js_tasks_api_result_reads_as_the_python_one() -> None:
    want = BUILDERS["mediapipe results"]()
    poses = read(str(FIXTURES / "mediapipe_js.json"), want.image_size)
    np.testing.assert_allclose(poses.points, want.points[:1])
    assert poses.confidence is not None
    np.testing.assert_allclose(poses.confidence, want.confidence[:1])  # type: ignore[index]
    assert poses.format == "mediapipe33" and poses.label == ("result 0, pose 0",)


@pytest.mark.parametrize("name", ["yolo labels", "mediapipe results"])
def test_normalised_files_need_the_image_size(name: str) -> None:
    where = re.escape(str(FIXTURES / READ[name]))  # the file, or the folder's first file
    with pytest.raises(InputFileError, match=rf"^{where}(/clip_0\.txt)?: poses\[0\]: "):
        read(str(FIXTURES / READ[name]))
    with pytest.raises(
        InputFileError, match=r"normalised to \[0, 1\]: give the image size with --image-size W H"
    ):
        read(str(FIXTURES / READ[name]))


def test_a_yolo_summary_normalised_by_the_image_needs_its_size(tmp_path: Path) -> None:
    """summary(normalize=True) divides keypoints and box by the image's width and height."""
    data = json.loads((FIXTURES / "yolo_summary.json").read_text())
    for item in data:
        item["box"] = {k: v / IMAGE_SIZE[k[0] == "y"] for k, v in item["box"].items()}
        for axis, size in zip("xy", IMAGE_SIZE, strict=True):
            item["keypoints"][axis] = [v / size for v in item["keypoints"][axis]]
    (path := tmp_path / "normalised.json").write_text(json.dumps(data))
    with pytest.raises(InputFileError, match="YOLO results"):
        read(str(path))
    want = BUILDERS["yolo summary"]()
    np.testing.assert_allclose(read(str(path), IMAGE_SIZE).points, want.points, atol=1e-9)


def test_yolo_label_lines_without_visibility_have_no_confidence(tmp_path: Path) -> None:
    """kpt_shape [17, 2]: x y per keypoint, no visibility."""
    values = [0, 0.5, 0.5, 0.2, 0.6] + [v for j in range(17) for v in (0.4 + j / 100, 0.3 + j / 50)]
    (path := tmp_path / "frame_9.txt").write_text(" ".join(f"{v:g}" for v in values) + "\n")
    poses = read(str(path), (100.0, 200.0))
    assert poses.confidence is None and poses.format == "coco17" and poses.label == ("frame_9.txt line 1",)
    np.testing.assert_allclose(poses.points[0, 1], [41.0, 64.0])


def _broken(data: Any, tmp_path: Path, name: str = "broken.json") -> str:
    path = tmp_path / name
    path.write_text(data if isinstance(data, str) else json.dumps(data))
    with pytest.raises(InputFileError) as info:
        read(str(path), (640.0, 480.0))
    message = str(info.value)
    assert str(path) in message and "Traceback" not in message
    return message


def test_broken_mmpose_files_are_refused_by_field(tmp_path: Path) -> None:
    data = json.loads((FIXTURES / "mmpose_video.json").read_text())
    data[2]["instances"][1]["keypoint_scores"] = data[2]["instances"][1]["keypoint_scores"][:5]
    assert "[2].instances[1].keypoint_scores: expected 17 scores, got 5" in _broken(data, tmp_path)
    data = json.loads((FIXTURES / "mmpose_video.json").read_text())
    data[0]["instances"][0]["keypoints"][3] = [1.0, 2.0, 0.5]  # 3D keypoints are no MMPose 2D output
    assert "[0].instances[0].keypoints: expected [x, y] rows" in _broken(data, tmp_path)
    data[0]["frame_id"] = "zero"
    assert "[0].frame_id: expected a frame number" in _broken(data, tmp_path)
    assert "no instances in any frame" in _broken([{"frame_id": 0, "instances": []}], tmp_path)


def test_broken_yolo_files_are_refused_by_line_and_field(tmp_path: Path) -> None:
    short = "0 0.5 0.5 0.1 0.1 " + " ".join(["0.3"] * 20)
    assert "line 1: expected class cx cy w h and 17 keypoints" in _broken(short, tmp_path, "a_1.txt")
    assert "line 2: expected finite numbers" in _broken("\n0 0.5 x", tmp_path, "a_2.txt")
    assert "line 1: expected finite numbers" in _broken(short.replace("0.3", "nan", 1), tmp_path, "a_3.txt")
    data = json.loads((FIXTURES / "yolo_summary.json").read_text())
    data[1]["keypoints"]["visible"] = ["high"] * 17
    assert "[1].keypoints.visible: expected a list of numbers" in _broken(data, tmp_path)


def test_broken_mediapipe_and_wholebody_files_are_refused(tmp_path: Path) -> None:
    data = json.loads((FIXTURES / "mediapipe_js.json").read_text())
    data["landmarks"][0][4]["y"] = "up"
    assert "[0] pose 0 landmark 4: expected numbers" in _broken(data, tmp_path)
    assert "no pose in any result" in _broken({"landmarks": [], "worldLandmarks": []}, tmp_path)
    data = json.loads((FIXTURES / "coco_wholebody.json").read_text())
    del data["annotations"][0]["face_kpts"]
    assert "face_kpts: a COCO-WholeBody annotation has all of" in _broken(data, tmp_path)


def test_a_folder_of_yolo_labels_names_the_file_that_needs_the_size(tmp_path: Path) -> None:
    shutil.copytree(FIXTURES / "yolo_labels", tmp_path / "labels")
    with pytest.raises(InputFileError, match=r"clip_0\.txt: poses\[0\]: YOLO label rows"):
        read(str(tmp_path / "labels"))


@pytest.mark.parametrize(
    ("name", "said", "fmt"),
    [("mmpose_video.json", "MMPose inferencer", "coco17"),
     ("mmpose_image.json", "MMPose inferencer", "halpe26"),
     ("yolo_summary.json", "Ultralytics YOLO", "coco17"),
     ("mediapipe_python.json", "MediaPipe", "mediapipe33"),
     ("mediapipe_js.json", "MediaPipe", "mediapipe33"),
     ("alphapose-results.json", "AlphaPose", "halpe26"),
     ("coco_wholebody.json", "COCO-WholeBody", "wholebody133")],
)  # fmt: skip
def test_each_file_posted_whole_is_told_what_it_is(name: str, said: str, fmt: str) -> None:
    hint = raw_output_hint(json.loads((FIXTURES / name).read_text()))
    assert hint is not None and said in hint and f'"{fmt}"' in hint and "repnet lift FILE" in hint
    assert 'POST /lift takes {"poses": [...]}' in hint


def test_an_empty_label_file_is_a_frame_without_a_person(tmp_path: Path) -> None:
    shutil.copytree(FIXTURES / "yolo_labels", tmp_path / "labels")
    (tmp_path / "labels" / "clip_1.txt").write_text("\n")
    poses = read(str(tmp_path / "labels"), IMAGE_SIZE)
    assert poses.frame.tolist() == [0, 2, 2] and len(poses.points) == 3


def test_a_blank_label_file_first_or_between_keeps_each_pose_its_label(tmp_path: Path) -> None:
    shutil.copytree(FIXTURES / "yolo_labels", tmp_path / "labels")
    (tmp_path / "labels" / "clip_1.txt").write_text("\n")
    (tmp_path / "labels" / "clip_00.txt").write_text("  \n")  # the first file: frame 0, no person
    poses = read(str(tmp_path / "labels"), IMAGE_SIZE)
    assert poses.frame.tolist() == [0, 2, 2] and len(poses.label) == len(poses.points) == 3
    assert [label.split(" ")[0] for label in poses.label] == ["clip_0.txt", "clip_2.txt", "clip_2.txt"]
