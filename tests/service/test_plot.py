"""repnet.io.plot: a blitted animation frame shows the same pose as a frame drawn in full."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from repnet.cli.main import EXIT_OK, EXIT_USAGE, main
from repnet.io.plot import animate_poses
from tests.conftest import POSE_3D, project


def _lifted(tmp_path: Path) -> list[dict[str, object]]:
    """Two lifted poses far apart in view: the test pose seen from the front and turned 70 degrees."""
    clip = {"poses": [{"keypoints": project(POSE_3D, yaw_deg=yaw).tolist()} for yaw in (0.0, 70.0)]}
    (tmp_path / "in.json").write_text(json.dumps(clip))
    assert (
        main(
            [
                "lift",
                str(tmp_path / "in.json"),
                "--local",
                "--temporal",
                "off",
                "-o",
                str(tmp_path / "out.json"),
            ]
        )
        == EXIT_OK
    )
    poses: list[dict[str, object]] = json.loads((tmp_path / "out.json").read_text())["poses"]
    return poses


def _frames(path: Path) -> list[np.ndarray]:
    from PIL import Image

    with Image.open(path) as image:
        out = []
        for k in range(image.n_frames):
            image.seek(k)
            out.append(np.asarray(image.convert("RGB"), dtype=np.int16))
        return out


def test_a_blitted_frame_matches_the_same_frame_drawn_in_full(tmp_path: Path) -> None:
    """Frame 1 of (A, B) is B moved onto A's still background; frame 0 of (B, A) is B drawn in full
    with the same views: the two images agree (up to the GIF palettes), and differ from A."""
    a, b = _lifted(tmp_path)
    item = lambda pose: (np.array(pose["input"]["keypoints"], float), pose, "frame")  # noqa: E731
    animate_poses(tmp_path / "ab.gif", "h36m17", [item(a), item(b)], "m", fps=5)
    animate_poses(tmp_path / "ba.gif", "h36m17", [item(b), item(a)], "m", fps=5)
    a_then_b, b_then_a = _frames(tmp_path / "ab.gif"), _frames(tmp_path / "ba.gif")
    differs = lambda x, y: float((np.abs(x - y).max(axis=-1) > 60).mean())  # noqa: E731  share of pixels
    assert differs(a_then_b[0], a_then_b[1]) > 0.002  # the pose moved
    assert differs(a_then_b[1], b_then_a[0]) < 0.0005
    assert differs(a_then_b[0], b_then_a[1]) < 0.0005


def test_plot_without_matplotlib_says_how_to_install_it_from_this_checkout(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    _lifted(tmp_path)
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # importing it fails as when it is absent
    assert main(["plot", str(tmp_path / "out.json"), "-o", str(tmp_path / "pose.png")]) == EXIT_USAGE
    err = capsys.readouterr().err
    root = Path(__file__).resolve().parent.parent.parent
    assert f"matplotlib is needed: {sys.executable} -m pip install -e '{root}[cli]'" in err
    assert "make serve" in err
