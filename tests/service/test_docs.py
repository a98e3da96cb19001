"""The documentation's snippets, run as written against a live service (only its address is changed),
and its links: every relative link of README.md and docs/*.md points at a file and heading that exist.
The Python client snippets of docs/API.md are run by tests/service/test_client.py."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from repnet.core.formats import FORMATS, MODEL_JOINTS, from_model_joints
from repnet.core.inputs import EXAMPLE_KEYPOINTS
from repnet.server.config import Settings, settings_table
from repnet.server.startup import load_dir_lifters, load_lifter
from tests.conftest import LiveService
from tests.service.page_examples import detector_pose

ROOT = Path(__file__).resolve().parents[2]
README = ROOT / "README.md"
API = ROOT / "docs" / "API.md"
IMAGE_SIZE = (1280.0, 720.0)  # the MediaPipe example's image, px


def fenced(path: Path, heading: str, language: str) -> str:
    """The first ```language block after `heading` in `path`, before the next heading of its level."""
    text = path.read_text()
    start = text.index(f"\n{heading}\n")
    level = heading.split(" ")[0]
    end = text.find(f"\n{level} ", start + len(heading) + 2)
    section = text[start : end if end > 0 else len(text)]
    opening = section.index(f"```{language}\n") + len(f"```{language}\n")
    return section[opening : section.index("\n```", opening)]


def write_detector_outputs(folder: Path) -> dict[str, Any]:
    """What the README's three commands read, made from the tests' person: an OpenPose --write_json
    folder of 3 frames, a COCO results list of the same 3 frames, and a MediaPipe POST /lift body."""
    (folder / "openpose_out").mkdir()
    yaws = [0.0, 10.0, 20.0]
    for i, yaw in enumerate(yaws):
        body = detector_pose("body25", yaw)
        flat = np.concatenate([body, np.full((len(body), 1), 0.9)], axis=1).ravel().tolist()
        people = {"version": 1.3, "people": [{"pose_keypoints_2d": flat}]}
        (folder / "openpose_out" / f"clip_{i:012d}_keypoints.json").write_text(json.dumps(people))
    results = []
    for i, yaw in enumerate(yaws):
        coco = np.concatenate([detector_pose("coco17", yaw), np.full((17, 1), 0.9)], axis=1)
        results.append({"image_id": i, "category_id": 1, "score": 0.9, "keypoints": coco.ravel().tolist()})
    (folder / "results.json").write_text(json.dumps(results))
    # MediaPipe's 33 landmarks: x, y normalised by the image size, z, visibility (0 where the model
    # has no joint for the landmark; MediaPipe always gives every row).
    points, found = from_model_joints(FORMATS["mediapipe33"], np.array(EXAMPLE_KEYPOINTS)[None])
    pixels = np.where(found[0][:, None], points[0], points[0][found[0]].mean(axis=0))
    rows = [[x / IMAGE_SIZE[0], y / IMAGE_SIZE[1], -0.2, 0.95 if ok else 0.0]
            for (x, y), ok in zip(pixels.tolist(), found[0].tolist(), strict=True)]  # fmt: skip
    body = {"format": "mediapipe33", "image_size": list(IMAGE_SIZE), "poses": [{"keypoints": rows}]}
    (folder / "mediapipe.json").write_text(json.dumps(body))
    return {"pixels": pixels, "visibility": [r[3] for r in rows]}


def test_readme_detector_commands_run_as_written(live_service: LiveService, tmp_path: Path) -> None:
    """README "Lift your detector's output": each command as printed, `repnet` being this checkout's
    CLI and the service the test's (its --url, curl's address)."""
    lines = [line for line in fenced(README, "## Lift your detector's output", "bash").splitlines()
             if line.strip() and not line.startswith("#")]  # fmt: skip
    assert [line.split()[0] for line in lines] == ["repnet", "repnet", "curl"]
    if shutil.which("curl") is None:
        pytest.skip("the MediaPipe command needs curl")
    made = write_detector_outputs(tmp_path)
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    (bin_dir / "repnet").write_text(f'#!/bin/sh\nexec "{sys.executable}" -m repnet.cli.main "$@"\n')
    (bin_dir / "repnet").chmod(0o755)
    env = {**os.environ, "PATH": f"{bin_dir}:{os.environ['PATH']}", "PYTHONPATH": str(ROOT)}
    host = live_service.http_url.removeprefix("http://")
    for line in lines:
        command = line.replace("repnet lift ", f"repnet lift --url {live_service.http_url} ")
        command = command.replace("localhost:8000", host)
        done = subprocess.run(["bash", "-c", command], cwd=tmp_path, env=env, capture_output=True,
                              text=True, timeout=120)  # fmt: skip
        assert done.returncode == 0, (command, done.stdout, done.stderr)

    for name in ("openpose_3d.json", "coco_3d.json"):
        poses = json.loads((tmp_path / name).read_text())["poses"]
        assert [(p["frame"], p["person"]) for p in poses] == [(0, 0), (1, 0), (2, 0)], name
        for pose in poses:
            assert np.array(pose["pose_3d"]).shape == (len(MODEL_JOINTS), 3)
            assert pose["warnings"] == [] and pose["reprojection_error_px"] < 15, (name, pose)
    mediapipe = json.loads((tmp_path / "mediapipe_3d.json").read_text())
    # The same landmarks in pixels give the same answer: image_size scaled them.
    in_pixels = {"format": "mediapipe33", "poses": [{"keypoints": made["pixels"].tolist(),
                                                     "confidence": made["visibility"]}]}  # fmt: skip
    direct = httpx.post(f"{live_service.http_url}/lift", json=in_pixels, timeout=30).json()
    np.testing.assert_allclose(mediapipe["poses"][0]["pose_3d"], direct["poses"][0]["pose_3d"], atol=1e-3)


def test_readme_adapt_commands_run_as_written(tmp_path: Path) -> None:
    """README "Adapt it to your detector": the adapt command as printed on the README's OpenPose
    folder, told to stop after two steps (the flags appended are the only change), and the folder it
    wrote served beside the bundled model under the name the README gives."""
    pytest.importorskip("torch", reason="repnet adapt needs the train extra")
    lines = [line for line in fenced(README, "## Adapt it to your detector", "bash").splitlines()
             if line.strip() and not line.startswith("#")]  # fmt: skip
    assert [line.split()[0] for line in lines] == ["pip", "repnet", "REPNET_MODEL_DIR=models"]
    assert ".[train]" in lines[0]
    write_detector_outputs(tmp_path)
    (tmp_path / "models").mkdir()
    short = f" --steps 2 --prior-poses 2000 --threads 1 --force --run-dir {tmp_path / 'run'}"
    command = lines[1].split("#")[0].strip().replace("repnet ", f"{sys.executable} -m repnet ", 1) + short
    done = subprocess.run(["bash", "-c", command], cwd=tmp_path, capture_output=True, text=True,
                          timeout=300, env={**os.environ, "PYTHONPATH": str(ROOT)})  # fmt: skip
    assert done.returncode == 0, (command, done.stdout, done.stderr)
    assert "before" in done.stdout and "after" in done.stdout
    settings = Settings(model_dir=tmp_path / "models")
    served = load_dir_lifters(settings, load_lifter(settings))
    assert [lifter.info.model_id for lifter in served] == ["adapted"]
    assert '"model": "adapted"' in lines[2]


def test_api_http_example_runs_as_written(live_service: LiveService) -> None:
    """docs/API.md, HTTP API: the curl example."""
    if shutil.which("curl") is None:
        pytest.skip("needs curl")
    command = fenced(API, "## HTTP API", "bash")
    command = command.replace("localhost:8000", live_service.http_url.removeprefix("http://"))
    done = subprocess.run(["bash", "-c", command], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    reply = json.loads(done.stdout)
    assert np.array(reply["poses"][0]["pose_3d"]).shape == (17, 3)


def test_api_grpc_example_runs_as_written(
    live_service: LiveService, capsys: pytest.CaptureFixture[str]
) -> None:
    """docs/API.md, gRPC API: the Python example with plain grpcio."""
    snippet = fenced(API, "## gRPC API", "python")
    snippet = snippet.replace('"localhost:50051"', repr(live_service.grpc_target))
    exec(compile(snippet, "docs/API.md", "exec"), {"__name__": "api_doc"})
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("repnet-") and lines[1:] == ["0 pose", "1 pose", "2 pose"]


def test_readme_python_example_runs_as_written(
    live_service: LiveService, capsys: pytest.CaptureFixture[str]
) -> None:
    """README "From Python": the example with repnet's clients, against a live service."""
    snippet = fenced(README, "## From Python", "python")
    snippet = snippet.replace('"http://localhost:8000"', repr(live_service.http_url))
    snippet = snippet.replace('"localhost:50051"', repr(live_service.grpc_target))
    exec(compile(snippet, "README.md", "exec"), {"__name__": "readme"})
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("(17, 3) ") and lines[0].endswith(" True")
    assert lines[1:] == ["0 (17, 3)", "1 (17, 3)", "2 (17, 3)"]


def slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped, spaces to hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


@pytest.mark.parametrize("doc", [README, *sorted((ROOT / "docs").glob("*.md"))], ids=lambda p: p.name)
def test_relative_links_point_at_existing_files_and_headings(doc: Path) -> None:
    broken = []
    for target in re.findall(r"\]\(([^)\s]+)\)", doc.read_text()):
        if re.match(r"[a-z]+:", target):
            continue  # an absolute URL
        path, _, anchor = target.partition("#")
        file = (doc.parent / path).resolve() if path else doc
        if not file.exists():
            broken.append(target)
        elif anchor and file.suffix == ".md":
            headings = re.findall(r"^#+ (.+)$", file.read_text(), re.MULTILINE)
            if anchor not in {slug(h) for h in headings}:
                broken.append(target)
    assert not broken, broken


def test_the_configuration_table_is_every_setting_with_its_default_as_generated() -> None:
    text = (ROOT / "docs" / "API.md").read_text()
    found = re.search(r"<!-- settings: .*? -->\n(.*?)\n<!-- end settings -->", text, re.S)
    assert found is not None, "docs/API.md has no generated settings table"
    assert found.group(1) == settings_table(), "run: python -m repnet.server.config, and paste it"
