"""`repnet video`: a real clip lifted end to end (in-process and through a live service) and written as
`repnet lift` writes, or drawn over the clip; a clip without people, a broken or missing file, a
missing extra: a message and an exit status, no traceback."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import av
import numpy as np
import pytest

from repnet.cli.main import EXIT_OK, EXIT_USAGE, main
from tests.conftest import LiveService

CLIP = Path(__file__).resolve().parents[1] / "fixtures" / "video" / "street640.mp4"


@pytest.fixture(scope="module")
def lifted(tmp_path_factory: pytest.TempPathFactory) -> dict:
    out = tmp_path_factory.mktemp("video") / "out.json"
    assert main(["video", str(CLIP), "--local", "-o", str(out)]) == EXIT_OK
    return json.loads(out.read_text())


def test_a_clip_is_lifted_as_a_tracked_sequence_at_its_frame_rate(lifted: dict) -> None:
    assert lifted["format"] == "mediapipe33" and lifted["temporal"] == "offline" and lifted["fps"] == 5.0
    assert lifted["video"] == {"source": str(CLIP), "width": 640, "height": 360, "fps": 5.0, "frames": 5}
    poses = lifted["poses"]
    assert [p["frame"] for p in poses] == [0, 1, 2, 3, 4] and {p["track_id"] for p in poses} == {"0"}
    pose = np.array(poses[0]["pose_3d"])  # (17, 3) mm
    assert pose.shape == (17, 3) and np.isfinite(pose).all()
    height = np.ptp(pose, axis=0).max()
    assert 1000 < height < 2200  # a person's size in mm
    assert all(p["temporal"] for p in poses)


def test_closer_views_find_the_smaller_people_and_each_is_a_track(tmp_path: Path) -> None:
    out = tmp_path / "out.json"
    assert main(["video", str(CLIP), "--local", "-o", str(out), "--zoom", "2"]) == EXIT_OK
    document = json.loads(out.read_text())
    poses = document["poses"]
    # 3 people in each of 5 frames; the one cut by the frame's right edge (person 2) mostly shows too
    # few joints to lift (skipped, named); the two others are each one track of the 5 frames
    skipped = document["skipped"]
    assert len(poses) + len(skipped) == 15 and len(skipped) >= 3 and all(s["person"] == 2 for s in skipped)
    whole = [t for t in {p["track_id"] for p in poses} if sum(p["track_id"] == t for p in poses) == 5]
    assert len(whole) == 2
    for track in whole:
        mine = [p for p in poses if p["track_id"] == track]
        assert [p["frame"] for p in mine] == [0, 1, 2, 3, 4] and {p["person"] for p in mine} in ({0}, {1})
        hips = np.array([np.nanmean(np.array(p["input"]["keypoints"][23:25], float), axis=0) for p in mine])
        assert np.abs(np.diff(hips[:, 0])).max() < 40  # px: one person followed, not a jump to another


def test_intrinsics_give_the_root_trajectory(tmp_path: Path) -> None:
    out = tmp_path / "out.json"
    args = ["video", str(CLIP), "--local", "-o", str(out), "--intrinsics", "500,500,320,180"]
    assert main(args) == EXIT_OK
    roots = np.array([p["root_camera_m"] for p in json.loads(out.read_text())["poses"]])
    assert roots.shape == (5, 3) and (roots[:, 2] > 1).all() and (roots[:, 0] > 0).all()  # right of centre


@pytest.mark.parametrize("suffix", [".bvh", ".csv", ".npz"])
def test_what_repnet_lift_writes(tmp_path: Path, suffix: str) -> None:
    out = tmp_path / f"out{suffix}"
    assert main(["video", str(CLIP), "--local", "-o", str(out)]) == EXIT_OK
    assert out.stat().st_size > 1000


def test_an_mp4_shows_the_clip_beside_the_3d_poses(tmp_path: Path) -> None:
    out = tmp_path / "out.mp4"
    assert main(["video", str(CLIP), "--local", "-o", str(out)]) == EXIT_OK
    with av.open(str(out)) as container:
        frames = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
    assert len(frames) == 5 and frames[0].shape == (360, 640 + 360, 3)
    panel = frames[0][:, 640:].astype(int)
    assert (panel.max(axis=2) > 150).sum() > 100  # the skeleton's lines on the dark panel
    assert main(["video", str(CLIP), "--local", "-o", str(out)]) == EXIT_USAGE  # exists: --overwrite


def test_the_service_lifts_what_the_process_lifts(
    lifted: dict, tmp_path: Path, live_service: LiveService
) -> None:
    out = tmp_path / "remote.json"
    assert main(["video", str(CLIP), "--url", live_service.http_url, "-o", str(out)]) == EXIT_OK
    remote = json.loads(out.read_text())["poses"]
    for a, b in zip(remote, lifted["poses"], strict=True):
        np.testing.assert_allclose(a["pose_3d"], b["pose_3d"], atol=1e-2)


def _blank_clip(path: Path, frames: int = 3) -> None:
    with av.open(str(path), "w") as container:
        stream = container.add_stream("libx264", rate=10)
        stream.width, stream.height, stream.pix_fmt = 320, 240, "yuv420p"
        for _ in range(frames):
            image = av.VideoFrame.from_ndarray(np.full((240, 320, 3), 120, np.uint8), format="rgb24")
            container.mux(stream.encode(image))
        container.mux(stream.encode(None))


def _fails(args: list[str], capsys: pytest.CaptureFixture[str], message: str) -> None:
    assert main(args) == EXIT_USAGE
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err, err


def test_a_clip_without_people_says_so(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    _blank_clip(blank := tmp_path / "blank.mp4")
    _fails(["video", str(blank), "--local"], capsys, f"{blank}: no person found in its 3 frames")


def test_a_broken_or_missing_file_says_so(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (broken := tmp_path / "broken.mp4").write_bytes(b"\x00\x00\x00\x18ftypmp42" + bytes(200))
    _fails(["video", str(broken), "--local"], capsys, f"{broken}: cannot open it as a video")
    _fails(["video", str(tmp_path / "none.mp4"), "--local"], capsys, "none.mp4: no such file")
    (text := tmp_path / "notes.mp4").write_text("not a video")
    _fails(["video", str(text), "--local"], capsys, f"{text}: cannot open it as a video")


def test_a_missing_extra_names_its_install(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setitem(sys.modules, "av", None)  # import av raises ImportError naming av
    _fails(["video", str(CLIP), "--local"], capsys, "[video]")


def test_flags_are_checked(capsys: pytest.CaptureFixture[str]) -> None:
    _fails(["video", str(CLIP), "--max-people", "0"], capsys, "--max-people must be at least 1")
    _fails(["video", str(CLIP), "-o", "out.txt"], capsys, "unknown output suffix")


def test_the_readmes_video_command_runs_as_written(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """README "From a video": its `repnet video` line on the test clip named as the README names it."""
    from tests.service.test_docs import README, fenced

    lines = [line.split("#")[0].split() for line in fenced(README, "## From a video", "bash").splitlines()]
    commands = [words for words in lines if words[:2] == ["repnet", "video"]]
    assert len(commands) == 1
    (tmp_path / commands[0][2]).write_bytes(CLIP.read_bytes())
    monkeypatch.chdir(tmp_path)
    assert main(commands[0][1:]) == EXIT_OK
    out = Path(commands[0][commands[0].index("-o") + 1])
    with av.open(str(out)) as container:
        assert sum(1 for _ in container.decode(video=0)) == 5


def test_a_camera_is_lifted_causally_as_it_is_read(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """`repnet video 0`: a camera (here the clip behind /dev/video0, as v4l2 would give its frames) is
    read once and lifted with the causal model, as a live camera must be; its -o .mp4 is drawn from
    the frames kept while reading."""
    from repnet.io import video

    real_open = av.open

    def open_device(source: str, *args: object, **options: object) -> object:
        if source == "/dev/video0":  # what v4l2 would give: the clip's frames, read once
            assert options == {"format": "v4l2"}
            return real_open(str(CLIP))
        return real_open(source, *args, **options)  # the .mp4 written

    monkeypatch.setattr(video, "device_path", lambda source: "/dev/video0" if source == "0" else None)
    monkeypatch.setattr(av, "open", open_device)
    out, drawn = tmp_path / "camera.json", tmp_path / "camera.mp4"
    assert main(["video", "0", "--local", "-o", str(out)]) == EXIT_OK
    found = json.loads(out.read_text())
    assert found["temporal"] == "causal" and found["video"]["frames"] == 5
    poses = found["poses"]
    assert [p["frame"] for p in poses] == [0, 1, 2, 3, 4] and all(p["temporal"] for p in poses)
    assert main(["video", "0", "--local", "-o", str(drawn)]) == EXIT_OK
    with real_open(str(drawn)) as container:
        assert sum(1 for _ in container.decode(video=0)) == 5
