"""The web page at GET /: how it is served, and the page itself in a real browser (Debian's chromium
through chromium-driver) against a running service. Screenshots go to runs/page/."""

from __future__ import annotations

import contextlib
import json
import math
import os
import re
import shutil
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient

from repnet.client.http import LiftClient
from repnet.client.tracker import assign_tracks
from repnet.core.errors import SPLIT_HINT
from repnet.core.formats import FORMATS, from_model_joints
from repnet.runtime.batchers import LiftBatcher
from repnet.runtime.lifter import Lifter
from repnet.server.app import build_app
from repnet.server.config import Settings
from repnet.server.http.page import ASSETS, CSP, STATIC_DIR, VENDOR
from repnet.server.metrics import Metrics
from tests.conftest import POSE_3D, TEMPORAL_MODES, live_settings, load_model, project, running_service
from tests.service.page_examples import EXAMPLES_PATH, build_examples, detector_pose

SHOTS = Path(__file__).resolve().parents[2] / "runs" / "page"
BODY_LIMIT = 64 * 1024


def test_page_and_its_files_are_served_with_a_same_origin_policy(client: TestClient) -> None:
    page = client.get("/")
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    assert page.headers["content-security-policy"] == CSP and "connect-src 'self'" in CSP
    assert page.headers["x-content-type-options"] == "nosniff"
    for name, media_type in ASSETS.items():
        asset = client.get(f"/ui/{name}")
        assert asset.status_code == 200 and asset.headers["content-type"] == media_type
        assert asset.content == (STATIC_DIR / name).read_bytes()
    assert client.get("/ui/..%2Fpage.py").status_code == 404
    assert client.get("/ui/index.html").status_code == 404  # only the listed files
    paths = client.get("/openapi.json").json()["paths"]
    assert "/" not in paths and "/ui/{name}" not in paths


def test_ui_false_serves_the_api_alone(
    engine: LiftBatcher, metrics: Metrics, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("REPNET_UI", "false")
    assert Settings().ui is False
    with TestClient(build_app(engine, metrics, Settings()), base_url="http://localhost") as client:
        assert client.get("/").status_code == 404 and client.get("/ui/page.js").status_code == 404
        assert client.get("/healthz").status_code == 200


def test_the_bundle_names_no_other_origin_and_no_inline_code() -> None:
    own = {name for name in ASSETS if not name.startswith(VENDOR)}
    files = {p.name: p.read_text() for p in STATIC_DIR.iterdir() if p.is_file()}
    assert set(files) == {*own, "index.html"}
    vendored = {p.relative_to(STATIC_DIR).as_posix() for p in (STATIC_DIR / VENDOR).iterdir()}
    assert vendored == {*ASSETS, "index.html"} - set(files) | {VENDOR + "LICENSE", VENDOR + "README.md"}
    for name, text in files.items():
        text = text.replace('xmlns="http://www.w3.org/2000/svg"', "")  # a name, never fetched
        assert not re.search(r"(https?:)?//[a-z0-9.-]+\.[a-z]{2,}", text, re.I), name
    html = files["index.html"]
    assert re.findall(r"<script[^>]*>", html) == ['<script type="module" src="/ui/page.js">']
    assert not re.search(r"\son[a-z]+=", html) and "style=" not in html
    scripts = "".join(files[n] for n in own if n.endswith(".js"))
    assert "innerHTML" not in scripts and "insertAdjacentHTML" not in scripts and "eval(" not in scripts
    assert set(re.findall(r"fetch\(\"([^\"]+)\"", scripts)) == {"/lift", "/v1/model", "/ui/examples.json"}


def test_bundled_examples_are_current() -> None:
    """Regenerate with python -m tests.service.page_examples."""
    assert json.loads(EXAMPLES_PATH.read_text()) == json.loads(json.dumps(build_examples()))


# ---- in the browser ----


@contextlib.contextmanager
def serving(lifter: Lifter, **changes: Any) -> Iterator[str]:
    """The service as `python -m repnet serve` runs it, with a small body limit for the upload test."""
    with running_service(live_settings(max_body_bytes=BODY_LIMIT, **changes), lifter) as service:
        yield service.http_url


@pytest.fixture(scope="module")
def page_url(lifter: Lifter) -> Iterator[str]:
    with serving(lifter) as url:
        yield url


@pytest.fixture(scope="module")
def driver() -> Iterator[Any]:
    """Headless chromium; skipped without it, failed instead under REQUIRE_BROWSER=1 (CI)."""
    chromium, chromedriver = shutil.which("chromium"), shutil.which("chromedriver")
    if chromium is None or chromedriver is None:
        message = "needs Debian's chromium and chromium-driver (apt-get install chromium chromium-driver)"
        if os.environ.get("REQUIRE_BROWSER") == "1":
            pytest.fail(message)
        pytest.skip(message)
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = chromium
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                "--window-size=1560,1250", "--force-device-scale-factor=1"):  # fmt: skip
        options.add_argument(arg)
    # performance: every request the page makes (tests/hardening/test_docs_offline.py)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL", "performance": "ALL"})
    browser = webdriver.Chrome(options=options, service=Service(executable_path=chromedriver))
    SHOTS.mkdir(parents=True, exist_ok=True)
    try:
        yield browser
    finally:
        browser.quit()


def open_page(driver: Any, url: str) -> None:
    driver.get(url)
    wait_for(driver, "return document.body.dataset.ready === 'true'")


def wait_for(driver: Any, script: str, timeout: float = 15) -> Any:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if value := driver.execute_script(script):
            return value
        time.sleep(0.05)
    raise AssertionError(f"timed out waiting for: {script}")


def lifts(driver: Any) -> int:
    return int(driver.execute_script("return Number(document.body.dataset.lifts || 0)"))


def wait_lift(driver: Any, before: int, timeout: float = 15) -> None:
    wait_for(driver, f"return Number(document.body.dataset.lifts || 0) > {before}", timeout)


def text_of(driver: Any, element_id: str) -> str:
    return str(driver.execute_script(f"return document.getElementById('{element_id}').textContent"))


# Pixel statistics of a canvas, computed in the page from getImageData: per colour of interest the
# number of pixels within a small distance of it and their mean x; and the bounding box of all that
# is not background.
PIXELS_JS = """
const canvas = document.getElementById(arguments[0]);
const {data, width, height} = canvas.getContext('2d').getImageData(0, 0, canvas.width, canvas.height);
const colours = {left: [47, 125, 246], right: [240, 72, 62], grid: [59, 68, 82],
                 reprojection: [242, 242, 242], imputed: [255, 176, 32]};
const out = {}; for (const k in colours) out[k] = {count: 0, x: 0};
let drawn = 0, x0 = width, x1 = 0, y0 = height, y1 = 0;
for (let i = 0; i < data.length; i += 4) {
  const [r, g, b] = [data[i], data[i + 1], data[i + 2]];
  const x = (i / 4) % width, y = Math.floor(i / 4 / width);
  if (Math.abs(r - 18) + Math.abs(g - 22) + Math.abs(b - 28) > 12) drawn++;
  for (const k in colours) {
    const c = colours[k];
    if (Math.abs(r - c[0]) + Math.abs(g - c[1]) + Math.abs(b - c[2]) < 30) {
      out[k].count++; out[k].x += x;
      if (k === 'left' || k === 'right') {  // the limbs' bounding box
        x0 = Math.min(x0, x); x1 = Math.max(x1, x); y0 = Math.min(y0, y); y1 = Math.max(y1, y);
      }
    }
  }
}
for (const k in out) out[k].x = out[k].count ? out[k].x / out[k].count : null;
out.drawn = drawn; out.box = [x0, y0, x1, y1]; out.hash = canvas.toDataURL();
return out;
"""


def pixels(driver: Any, canvas: str) -> dict[str, Any]:
    return dict(driver.execute_script(PIXELS_JS, canvas))


def shown_numbers(driver: Any) -> dict[str, str]:
    ids = ("model", "scale", "rotation", "error", "plausibility", "imputed", "derived")
    return {k: text_of(driver, f"num-{k}") for k in ids}


def assert_numbers_match(shown: dict[str, str], reply: dict[str, Any], joints: list[str]) -> None:
    """The page rounds for display: each number equals the API's to within half its last digit."""
    pose = reply if "scale" in reply else reply["poses"][0]
    assert float(shown["scale"]) == pytest.approx(pose["scale"], rel=5e-5)
    rows = [[float(v) for v in line.split()] for line in shown["rotation"].splitlines()]
    np.testing.assert_allclose(rows, pose["rotation"], atol=5e-5 + 1e-9)
    assert float(shown["error"]) == pytest.approx(pose["reprojection_error_px"], abs=5e-3 + 1e-9)
    if pose["plausibility"] is None:
        assert shown["plausibility"].startswith("— (the model has no plausibility output)")
    else:
        assert float(shown["plausibility"].split()[0]) == pytest.approx(pose["plausibility"], abs=5e-4)
    for key in ("imputed", "derived"):
        names = [j for j, flag in zip(joints, pose[key], strict=True) if flag]
        assert shown[key] == (", ".join(names) or "none")


def lift_api(url: str, body: Any) -> dict[str, Any]:
    reply = httpx.post(f"{url}/lift", json=body, timeout=10)
    assert reply.status_code == 200, reply.text
    return dict(reply.json())


def page_mode(driver: Any) -> str:
    """The temporal mode the page lifted with (offline by default for a sequence, else causal until
    the offline model ships)."""
    return str(driver.execute_script("return document.body.dataset.temporal"))


def tracked(body: dict[str, Any], frames: list[int], mode: str, fps: float) -> dict[str, Any]:
    """`body` as the page sends a sequence: each pose with its track (repnet.client.tracker, which the page's
    track.js follows) and frame number, with `temporal` and `fps`."""
    points = np.array(
        [[[np.nan, np.nan] if r is None else r[:2] for r in p["keypoints"]] for p in body["poses"]]
    )
    tracks = assign_tracks(np.array(frames), points, fps)
    poses = [
        {**p, "track_id": str(t), "frame": f}
        for p, t, f in zip(body["poses"], tracks.tolist(), frames, strict=True)
    ]
    return {**body, "poses": poses, "temporal": mode, "fps": fps}


def test_page_lifts_an_example_draws_it_and_shows_the_api_numbers(driver: Any, page_url: str) -> None:
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.actions.wheel_input import ScrollOrigin
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import Select

    open_page(driver, page_url)
    before = lifts(driver)
    Select(driver.find_element(By.ID, "example")).select_by_index(1)
    wait_lift(driver, before)
    example = build_examples()[0]["data"]
    reply = lift_api(page_url, example)
    shown = shown_numbers(driver)
    assert shown["model"] == reply["model_id"]
    assert_numbers_match(shown, reply, reply["joints"])
    front = pixels(driver, "view3d")
    # Both sides drew, apart: the subject faces the camera, so its left limbs are on the image right.
    assert front["left"]["count"] > 300 and front["right"]["count"] > 300, front
    assert front["left"]["x"] - front["right"]["x"] > 40, front
    assert front["grid"]["count"] > 500, front
    flat = pixels(driver, "view2d")
    assert flat["reprojection"]["count"] > 100 and flat["left"]["count"] > 100, flat
    driver.save_screenshot(str(SHOTS / "example-front.png"))
    driver.find_element(By.ID, "view3d").screenshot(str(SHOTS / "3d-front.png"))
    driver.find_element(By.ID, "view-side").click()
    side = pixels(driver, "view3d")
    assert side["left"]["count"] > 150 and side["right"]["count"] > 150, side
    assert abs(side["left"]["x"] - side["right"]["x"]) < abs(front["left"]["x"] - front["right"]["x"]) / 2
    driver.find_element(By.ID, "view3d").screenshot(str(SHOTS / "3d-side.png"))
    canvas = driver.find_element(By.ID, "view3d")
    ActionChains(driver).click_and_hold(canvas).move_by_offset(-80, 30).release().perform()
    dragged = pixels(driver, "view3d")
    assert dragged["hash"] != side["hash"]
    height = dragged["box"][3] - dragged["box"][1]
    ActionChains(driver).scroll_from_origin(ScrollOrigin.from_element(canvas), 0, -400).perform()
    zoomed = pixels(driver, "view3d")
    assert zoomed["box"][3] - zoomed["box"][1] > 1.2 * height, (dragged["box"], zoomed["box"])
    origin = page_url.rstrip("/")
    resources = driver.execute_script("return performance.getEntriesByType('resource').map(e => e.name)")
    assert resources and all(r.startswith(origin + "/") for r in resources), resources
    errors = [e for e in driver.get_log("browser") if e["level"] == "SEVERE"]
    assert not errors, errors


def test_format_choice_relifts_and_shows_the_services_warning(driver: Any, page_url: str) -> None:
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import Select

    open_page(driver, page_url)
    before = lifts(driver)
    Select(driver.find_element(By.ID, "example")).select_by_index(2)  # the COCO-17 detector result
    wait_lift(driver, before)
    assert text_of(driver, "format-warnings") == ""
    assert text_of(driver, "num-imputed") == "spine, head"
    assert text_of(driver, "num-derived") == "pelvis, thorax"
    triples = np.array(build_examples()[1]["data"][0]["keypoints"]).reshape(-1, 3)
    body = {"format": "h36m17", "poses": [{"keypoints": triples[:, :2].tolist(),
                                           "confidence": triples[:, 2].tolist()}]}  # fmt: skip
    reply = lift_api(page_url, body)
    assert reply["poses"][0]["warnings"], "the service no longer warns about coco17 sent as h36m17"
    before = lifts(driver)
    Select(driver.find_element(By.ID, "format")).select_by_value("h36m17")
    wait_lift(driver, before)
    assert text_of(driver, "format-warnings") == "".join(reply["poses"][0]["warnings"])
    assert_numbers_match(shown_numbers(driver), reply["poses"][0], reply["joints"])
    driver.save_screenshot(str(SHOTS / "format-warning.png"))


def openpose_frames(tmp_path: Path, yaws: list[float]) -> list[Path]:
    paths = []
    for i, yaw in enumerate(yaws):
        body = detector_pose("body25", yaw)
        flat = np.concatenate([body, np.full((len(body), 1), 0.9)], axis=1).ravel().tolist()
        path = tmp_path / f"walk_{i:012d}_keypoints.json"
        path.write_text(json.dumps({"version": 1.3, "people": [{"pose_keypoints_2d": flat}]}))
        paths.append(path)
    return paths


def test_openpose_frames_upload_and_the_player_steps_through_them(
    driver: Any, page_url: str, tmp_path: Path
) -> None:
    from selenium.webdriver.common.by import By

    yaws = [float(y) for y in range(-60, 61, 10)]
    paths = openpose_frames(tmp_path, yaws)
    open_page(driver, page_url)
    before = lifts(driver)
    driver.find_element(By.ID, "file").send_keys("\n".join(str(p) for p in reversed(paths)))
    wait_lift(driver, before)
    assert driver.find_element(By.ID, "player").is_displayed()
    assert text_of(driver, "frame-label") == f"frame 0 (1 / {len(yaws)})"  # numbers from 0, as the CLI's
    body = {"format": "body25", "poses": [json.loads(p.read_text())["people"][0] for p in paths]}
    body["poses"] = [
        {"keypoints": np.array(p["pose_keypoints_2d"]).reshape(-1, 3)[:, :2].tolist(),
         "confidence": np.array(p["pose_keypoints_2d"]).reshape(-1, 3)[:, 2].tolist()}
        for p in body["poses"]
    ]  # fmt: skip
    reply = lift_api(page_url, tracked(body, list(range(len(yaws))), page_mode(driver), 30.0))
    assert all(p["temporal"] and p["track_id"] == "0" for p in reply["poses"])
    assert_numbers_match(shown_numbers(driver), reply["poses"][0], reply["joints"])
    assert text_of(driver, "num-track") == f"0, temporal {page_mode(driver)}"
    first = pixels(driver, "view3d")["hash"]
    driver.find_element(By.ID, "next").click()
    assert text_of(driver, "frame-label") == f"frame 1 (2 / {len(yaws)})"
    assert_numbers_match(shown_numbers(driver), reply["poses"][1], reply["joints"])
    assert pixels(driver, "view3d")["hash"] != first
    driver.execute_script("const s = document.getElementById('frame'); s.value = '6';"
                          "s.dispatchEvent(new Event('input'));")  # fmt: skip
    assert text_of(driver, "frame-label") == f"frame 6 (7 / {len(yaws)})"
    assert_numbers_match(shown_numbers(driver), reply["poses"][6], reply["joints"])
    driver.save_screenshot(str(SHOTS / "openpose-frame7.png"))
    driver.execute_script("document.getElementById('fps').value = '20'")
    driver.find_element(By.ID, "play").click()
    wait_for(driver, "return document.getElementById('frame').value === '9'", timeout=5)
    driver.find_element(By.ID, "play").click()  # pause
    assert text_of(driver, "play") == "play"


def test_npz_upload_is_read_as_the_cli_reads_it(driver: Any, page_url: str, tmp_path: Path) -> None:
    from selenium.webdriver.common.by import By

    points = np.stack([detector_pose("coco17", y) for y in (0.0, 30.0, 60.0)])
    points[1, 9] = np.nan  # a missing left wrist
    path = tmp_path / "poses.npz"
    np.savez_compressed(path, keypoints=points, format=np.array("coco17"))
    open_page(driver, page_url)
    before = lifts(driver)
    driver.find_element(By.ID, "file").send_keys(str(path))
    wait_lift(driver, before)
    body = {
        "format": "coco17",
        "poses": [
            {"keypoints": [None if np.isnan(p).any() else p.tolist() for p in pose]} for pose in points
        ],
    }
    reply = lift_api(page_url, tracked(body, [0, 1, 2], page_mode(driver), 30.0))
    driver.find_element(By.ID, "next").click()
    assert text_of(driver, "frame-label") == "frame 1 (2 / 3)"
    assert_numbers_match(shown_numbers(driver), reply["poses"][1], reply["joints"])
    assert "left_wrist" in text_of(driver, "num-imputed")


def test_an_npz_that_inflates_past_the_limit_is_refused_unread(
    driver: Any, page_url: str, tmp_path: Path
) -> None:
    """A small NPZ of a huge array (zeros deflate 1000:1) is refused by its zip directory's sizes
    before anything is inflated (issue 30: the page froze at 2.7 GB); the page goes on working."""
    from selenium.webdriver.common.by import By

    limit = httpx.get(f"{page_url}/v1/model", timeout=10).json()["limits"]["max_body_bytes"]
    path = tmp_path / "bomb.npz"
    np.savez_compressed(path, keypoints=np.zeros((4 * limit // (17 * 2 * 8) + 1, 17, 2)))
    assert path.stat().st_size < limit  # the file itself passes the size check
    open_page(driver, page_url)
    driver.find_element(By.ID, "file").send_keys(str(path))
    wait_for(driver, "return document.getElementById('file-error').textContent.length > 0")
    assert f"more than the {4 * limit} this page reads" in text_of(driver, "file-error")
    driver.save_screenshot(str(SHOTS / "error-npz-inflated.png"))
    small = tmp_path / "poses.npz"
    np.savez_compressed(small, keypoints=np.stack([detector_pose("coco17", 0.0)]), format=np.array("coco17"))
    before = lifts(driver)
    driver.execute_script("document.getElementById('file').value = '';")  # a new pick, not one more file
    driver.find_element(By.ID, "file").send_keys(str(small))
    wait_lift(driver, before)
    assert text_of(driver, "file-error") == ""


def test_bad_inputs_show_the_api_error_next_to_the_field(driver: Any, page_url: str, tmp_path: Path) -> None:
    from selenium.webdriver.common.by import By

    open_page(driver, page_url)

    def paste(text: str, threshold: str = "") -> None:
        for element_id, value in (("paste", text), ("threshold", threshold)):
            driver.execute_script("document.getElementById(arguments[0]).value = arguments[1]", element_id,
                                  value)  # fmt: skip
        driver.find_element(By.ID, "lift-paste").click()

    def api_messages(body: Any) -> list[str]:
        reply = httpx.post(f"{page_url}/lift", json=body, timeout=10)
        assert reply.status_code == 422
        return [item["message"] for item in reply.json()["detail"]]

    paste("[[1, 2], [3, 4]]")
    expected = api_messages({"poses": [{"keypoints": [[1, 2], [3, 4]]}], "format": "h36m17"})
    wait_for(driver, "return document.getElementById('paste-error').textContent.length > 0")
    assert text_of(driver, "paste-error") == "".join(expected)
    assert expected == ["poses[0].keypoints: format h36m17 has 17 joints, got 2"]
    driver.save_screenshot(str(SHOTS / "error-joint-count.png"))

    pose = detector_pose("h36m17", 0.0).tolist()
    paste(json.dumps(pose), threshold="1.5")
    wait_for(driver, "return document.getElementById('threshold-error').textContent.length > 0")
    threshold_messages = api_messages({"poses": [{"keypoints": pose}], "confidence_threshold": 1.5})
    assert text_of(driver, "threshold-error") == "".join(threshold_messages)
    assert text_of(driver, "paste-error") == ""

    hostile = '<img src=x id=injected onerror="document.title=1">'
    paste(json.dumps({"keypoints": pose, "format": hostile}))
    wait_for(driver, "return document.getElementById('format-error').textContent.length > 0")
    assert hostile in text_of(driver, "format-error")  # shown as text, not parsed as HTML
    assert driver.execute_script("return document.getElementById('injected')") is None

    paste("{not json")
    wait_for(driver, "return document.getElementById('paste-error').textContent.startsWith('not JSON')")

    big = tmp_path / "big.json"
    big.write_text(json.dumps([pose] * 300))
    assert big.stat().st_size > BODY_LIMIT
    driver.find_element(By.ID, "file").send_keys(str(big))
    wait_for(driver, "return document.getElementById('file-error').textContent.length > 0")
    assert text_of(driver, "file-error") == (
        f"file big.json has {big.stat().st_size} bytes, more than the {BODY_LIMIT}-byte limit of a /lift "
        f"body; {SPLIT_HINT}"
    )
    driver.save_screenshot(str(SHOTS / "error-file-limit.png"))


def test_page_shows_the_plausibility_of_a_model_that_has_it(driver: Any, tmp_path: Path) -> None:
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import Select

    pytest.importorskip("onnx")
    from tests.service.test_plausibility import build_model

    plausible = load_model(build_model(tmp_path / "plausible.onnx"))
    with serving(plausible) as url:
        open_page(driver, url)
        assert text_of(driver, "model-plausibility") == "rates how plausible each 3D pose is"
        help_text = driver.find_element(By.ID, "model-plausibility").get_attribute("title")
        assert "more plausible than 30 % of real poses" in help_text
        before = lifts(driver)
        Select(driver.find_element(By.ID, "example")).select_by_index(4)  # the 36-frame sequence
        wait_lift(driver, before)
        frames = build_examples()[3]["data"]
        body = {"format": "body25", "poses": [
            {"keypoints": np.array(f["people"][0]["pose_keypoints_2d"]).reshape(-1, 3)[:, :2].tolist()}
            for f in frames]}  # fmt: skip
        reply = lift_api(
            url, tracked(body, list(range(len(frames))), page_mode(driver), 12.0)
        )  # the example's fps
        assert driver.execute_script("return document.getElementById('fps').value") == "12"
        for index in (0, 9):
            driver.execute_script("const s = document.getElementById('frame'); s.value = arguments[0];"
                                  "s.dispatchEvent(new Event('input'));", str(index))  # fmt: skip
            pose = reply["poses"][index]
            assert pose["plausibility"] is not None
            assert_numbers_match(shown_numbers(driver), pose, reply["joints"])
            percent = math.floor(100 * pose["plausibility"] + 0.5)  # JavaScript's Math.round
            expected = f"more plausible than {percent} % of real poses"
            assert expected in text_of(driver, "num-plausibility")
        driver.save_screenshot(str(SHOTS / "plausibility-frame10.png"))


def test_cli_output_and_coco_annotations_files_are_read(driver: Any, page_url: str, tmp_path: Path) -> None:
    from selenium.webdriver.common.by import By

    from repnet.cli.main import EXIT_OK, main

    coco = np.stack([detector_pose("coco17", y) for y in (10.0, 40.0)])
    source = tmp_path / "poses.json"
    source.write_text(json.dumps({"keypoints": coco.tolist(), "format": "coco17"}))
    out = tmp_path / "lifted.json"
    assert main(["lift", str(source), "--local", "-o", str(out)]) == EXIT_OK
    lifted = json.loads(out.read_text())
    open_page(driver, page_url)
    before = lifts(driver)
    driver.find_element(By.ID, "file").send_keys(str(out))
    wait_lift(driver, before)
    assert "repnet lift output: 2 poses" in text_of(driver, "status")
    driver.find_element(By.ID, "next").click()
    assert_numbers_match(shown_numbers(driver), lifted["poses"][1], lifted["joints"])  # the CLI's own answer

    flags = np.full((17, 1), 2.0)
    flags[9] = 0  # left wrist not labelled
    annotation = {"id": 7, "image_id": 3, "num_keypoints": 16,
                  "keypoints": np.concatenate([coco[0], flags], axis=1).ravel().tolist()}  # fmt: skip
    path = tmp_path / "person_keypoints.json"
    path.write_text(json.dumps({"images": [{"id": 3}], "annotations": [annotation]}))
    before = lifts(driver)
    driver.execute_script("document.getElementById('file').value = ''")  # chromedriver adds to a selection
    driver.find_element(By.ID, "file").send_keys(str(path))
    wait_lift(driver, before)
    keypoints = [None if j == 9 else p.tolist() for j, p in enumerate(coco[0])]
    reply = lift_api(page_url, {"format": "coco17", "poses": [{"keypoints": keypoints}]})
    assert_numbers_match(shown_numbers(driver), reply["poses"][0], reply["joints"])
    assert "left_wrist" in text_of(driver, "num-imputed")


def test_a_coco_file_with_unusable_people_lifts_the_others_and_names_the_skipped(
    driver: Any, page_url: str, tmp_path: Path
) -> None:
    from selenium.webdriver.common.by import By

    coco = np.stack([detector_pose("coco17", y) for y in (10.0, 40.0)])
    visible = np.full((17, 1), 2.0)
    unlabelled = np.zeros((17, 3))  # num_keypoints 0, as every COCO annotation file has some
    annotations = [
        {"id": 11, "image_id": 5, "keypoints": np.concatenate([coco[0], visible], 1).ravel().tolist()},
        {"id": 12, "image_id": 5, "num_keypoints": 0, "keypoints": unlabelled.ravel().tolist()},
        {"id": 13, "image_id": 6, "keypoints": np.concatenate([coco[1], visible], 1).ravel().tolist()},
    ]
    path = tmp_path / "person_keypoints.json"
    path.write_text(json.dumps({"images": [{"id": 5}, {"id": 6}], "annotations": annotations}))
    open_page(driver, page_url)
    before = lifts(driver)
    driver.find_element(By.ID, "file").send_keys(str(path))
    wait_lift(driver, before)
    assert "lifted 2 poses, skipped 1" in text_of(driver, "status")
    skipped = text_of(driver, "skipped")
    assert skipped.startswith("skipped poses[1] (image_id 5, id 12): keypoints: 0 of 17"), skipped
    assert text_of(driver, "num-error") != "—"  # the first usable pose is shown
    driver.save_screenshot(str(SHOTS / "coco-skipped.png"))

    every = [{**a, "keypoints": unlabelled.ravel().tolist()} for a in annotations]  # nothing usable
    path.write_text(json.dumps({"images": [{"id": 5}, {"id": 6}], "annotations": every}))
    driver.execute_script("document.getElementById('file').value = ''")
    driver.find_element(By.ID, "file").send_keys(str(path))
    wait_for(driver, "return document.getElementById('status').textContent.includes('no pose')", 15)
    assert "0 of 17" in text_of(driver, "file-error")
    assert text_of(driver, "skipped") == ""


STILLS_JS = """
const done = arguments[arguments.length - 1];
import("/ui/lift.js").then((m) => done(arguments[0].map((c) => m.stillsReason(c[0], c[1]))))
  .catch((err) => done({error: String(err)}));
"""


def test_unrelated_images_are_lifted_one_by_one_and_numbered_ones_as_a_clip(
    driver: Any, page_url: str, tmp_path: Path
) -> None:
    from selenium.webdriver.common.by import By

    from repnet.cli.lift import stills_reason

    cases = [
        ["image ids", [397133, 37777, 252219]], ["image ids", [0, 1, 2, 10, 11]], ["image ids", [0, 2, 4]],
        ["file names", [3, 40, 41, 90]], ["image names", [0, 1]], [None, [5, 90]], ["image ids", [7, 7]],
    ]  # fmt: skip
    open_page(driver, page_url)
    assert driver.execute_async_script(STILLS_JS, cases) == [stills_reason(*c) for c in cases]
    coco = detector_pose("coco17", 10.0)
    for ids, name in (([397133, 37777, 252219, 87038], "stills.json"), ([40, 41, 42, 43], "clip.json")):
        flat = [
            np.concatenate([coco + [k + 600.0 * person, 0.0], np.full((17, 1), 0.9)], 1).ravel().tolist()
            for k in range(len(ids))
            for person in range(3)
        ]
        results = [
            {"image_id": ids[n // 3], "category_id": 1, "score": 0.9, "keypoints": keypoints}
            for n, keypoints in enumerate(flat)
        ]
        path = tmp_path / name
        path.write_text(json.dumps(results))
        before = lifts(driver)
        driver.execute_script("document.getElementById('file').value = ''")
        driver.find_element(By.ID, "file").send_keys(str(path))
        wait_lift(driver, before)
        status = text_of(driver, "status")
        if name == "stills.json":
            assert "4 still images (image ids not consecutive): lifted one by one" in status, status
            assert page_mode(driver) == "off" and "track" not in status and "assuming" not in status
        else:
            assert "still images" not in status and page_mode(driver) != "off", status
            assert "3 track(s)" in status and "4 frames (image ids in sequence): assuming 30 fps" in status


# ---- sequences: tracks, the temporal control, clips cut into requests ----

TRACK_JS = """
const done = arguments[arguments.length - 1];
import("/ui/track.js").then((m) => done({
  tracks: arguments[0].map((c) => m.assignTracks(c.frames, c.poses, c.fps, c.max_gap_s)),
  parts: arguments[1].map((c) => m.splitClip(c.tracks, c.frames, c.reach, c.most)),
  reach: arguments[2].map((c) => m.reach(c.contract, c.fps)),
})).catch((err) => done({error: String(err)}));
"""


def crowd(frames: int, seed: int = 0) -> list[list[np.ndarray]]:
    """Per frame the BODY_25 poses of two people walking past each other: B missing in frames 40-44,
    a newcomer C far right from frame 60, the detector's order shuffled."""
    rng = np.random.default_rng(seed)
    found = []
    for f in range(frames):
        a = detector_pose("body25", 2.0 * f) + [2.0 * f, 0.0] + rng.normal(0, 1.5, (25, 2))
        b = detector_pose("body25", -2.0 * f) + [500.0 - 2.0 * f, 0.0] + rng.normal(0, 1.5, (25, 2))
        c = detector_pose("body25", 90.0) + [1500.0, 0.0]
        people = [a] + ([] if 40 <= f < 45 else [b]) + ([c] if f >= 60 else [])
        found.append([people[k] for k in rng.permutation(len(people))])
    return found


def test_the_pages_tracker_and_cuts_follow_the_services_rules(driver: Any, page_url: str) -> None:
    from repnet.client.chunks import split_clip
    from repnet.core.contract import Contract

    open_page(driver, page_url)
    clips = []
    for fps, frames in ((30.0, 80), (25.0, 50)):  # 25 fps: the gap rounds half to even (12.5 -> 12)
        people = crowd(frames, seed=int(fps))
        numbers = [f for f, found in enumerate(people) for _ in found]
        poses = [p for found in people for p in found]
        if fps == 25.0:  # a gap of 13 frames ends a track at 25 fps
            keep = [k for k, f in enumerate(numbers) if not 20 <= f < 33]
            numbers, poses = [numbers[k] for k in keep], [poses[k] for k in keep]
        clips.append((numbers, poses, fps))
    rules = httpx.get(f"{page_url}/v1/model").json()["rules"]  # what the page reads of the service
    rows = [
        {
            "frames": n,
            "fps": fps,
            "max_gap_s": rules["max_gap_s"],
            "poses": [{"keypoints": p.tolist()} for p in poses],
        }
        for n, poses, fps in clips
    ]
    rng = np.random.default_rng(4)
    cuts = []
    for reach, most in (((48, 0), 60), ((24, 24), 55), ((0, 0), 7)):
        tracks = [None if k % 17 == 0 else f"t{k % 3}" for k in range(240)]
        frames = [int(f) for f in rng.integers(0, 400, 240)]
        frames = [f for f in dict.fromkeys(frames)][:200]  # one pose per frame and track is enough here
        cuts.append({"tracks": tracks[: len(frames)], "frames": frames, "reach": list(reach), "most": most})
    contracts = [Contract(m, 50.0, 81, 60.0) for m in ("causal", "offline")] + [
        Contract("offline", 25.0, 27, 30.0)
    ]
    reaches = [
        {"contract": c.__dict__, "fps": fps} for c in contracts for fps in (12.0, 25.0, 30.0, 59.94, 100.0)
    ]
    got = driver.execute_async_script(TRACK_JS, rows, cuts, reaches)
    assert "error" not in got, got
    for (numbers, poses, fps), tracks in zip(clips, got["tracks"], strict=True):
        expected = assign_tracks(np.array(numbers), np.stack(poses), fps)
        assert tracks == expected.tolist()
        assert len(set(tracks)) >= 3
    for cut, parts in zip(cuts, got["parts"], strict=True):
        expected = split_clip(cut["tracks"], np.array(cut["frames"]), tuple(cut["reach"]), cut["most"])
        assert [p["send"] for p in parts] == [e.send.tolist() for e in expected]
        assert [p["keep"] for p in parts] == [e.keep.tolist() for e in expected]
    for entry, value in zip(reaches, got["reach"], strict=True):
        assert tuple(value) == Contract(**entry["contract"]).reach(entry["fps"]), entry


def openpose_crowd(tmp_path: Path, people: list[list[np.ndarray]]) -> list[Path]:
    paths = []
    for f, found in enumerate(people):
        flat = [np.concatenate([p, np.full((25, 1), 0.9)], axis=1).ravel().tolist() for p in found]
        path = tmp_path / f"crowd_{f:012d}_keypoints.json"
        path.write_text(json.dumps({"version": 1.3, "people": [{"pose_keypoints_2d": k} for k in flat]}))
        paths.append(path)
    return paths


def test_a_crowded_sequence_longer_than_a_request_is_tracked_cut_and_followed(
    driver: Any, lifter: Lifter, tmp_path: Path
) -> None:
    """100 frames of three people, in requests of at most 60 poses: the page's answers are those the
    Python client gets from the same cuts (which answer as one request: test_client, test_cli)."""
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import Select

    people = crowd(100)
    paths = openpose_crowd(tmp_path, people)
    with serving(lifter, max_temporal_poses=60) as url:
        open_page(driver, url)
        before = lifts(driver)
        driver.find_element(By.ID, "file").send_keys("\n".join(str(p) for p in paths))
        wait_lift(driver, before, timeout=60)
        mode = page_mode(driver)
        requests = int(re.search(r"in (\d+) requests", text_of(driver, "status")).group(1))  # type: ignore[union-attr]
        assert requests >= 4, text_of(driver, "status")
        numbers = [f for f, found in enumerate(people) for _ in found]
        poses = [p for found in people for p in found]
        tracks = [str(t) for t in assign_tracks(np.array(numbers), np.stack(poses), 30.0).tolist()]
        confidence = np.full((len(poses), 25), 0.9)
        with LiftClient(url) as client:
            results = client.lift_batch(np.stack(poses), format="body25", confidence=confidence,
                                        temporal=mode, fps=30.0, track_ids=tracks,
                                        frames=np.array(numbers))  # fmt: skip
        joints = list(results[0].joints)
        longest = max(set(tracks), key=tracks.count)
        assert driver.find_element(By.ID, "track").is_displayed()
        assert (
            Select(driver.find_element(By.ID, "track")).first_selected_option.get_attribute("value")
            == longest
        )

        def check(frame: int, track: str) -> None:
            go_to(driver, frame)
            k = next(
                i for i, (f, t) in enumerate(zip(numbers, tracks, strict=True)) if f == frame and t == track
            )
            reply = {
                name: getattr(results[k], name) for name in ("scale", "reprojection_error_px", "plausibility")
            }
            reply.update(
                {n: np.asarray(getattr(results[k], n)).tolist() for n in ("rotation", "imputed", "derived")}
            )
            assert_numbers_match(shown_numbers(driver), reply, joints)
            assert text_of(driver, "num-track") == f"{track}, temporal {mode}"

        for frame in (0, 50, 99):
            check(frame, longest)
        driver.save_screenshot(str(SHOTS / "crowd-track-frame100.png"))
        pelvis = FORMATS["body25"].joint_names.index("mid_hip")
        in_30 = [k for k, f in enumerate(numbers) if f == 30]
        b_track = tracks[
            min(in_30, key=lambda k: abs(poses[k][pelvis, 0] - (512 + 500 - 60)))
        ]  # B walks left
        assert b_track != longest
        Select(driver.find_element(By.ID, "track")).select_by_value(b_track)
        check(30, b_track)
        go_to(driver, 42)  # B is not found in frames 40-44
        assert text_of(driver, "num-model") == f"track {b_track} is not in this frame"
        driver.save_screenshot(str(SHOTS / "crowd-track-missing.png"))


def go_to(driver: Any, index: int) -> None:
    driver.execute_script("const s = document.getElementById('frame'); s.value = arguments[0];"
                          "s.dispatchEvent(new Event('input'));", str(index))  # fmt: skip


@pytest.mark.parametrize("mode", ["off", *TEMPORAL_MODES])
def test_the_temporal_control_and_the_frame_rate_lift_the_sequence_again(
    driver: Any, page_url: str, tmp_path: Path, mode: str
) -> None:
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import Select

    yaws = [float(y) for y in range(-40, 41, 5)]
    paths = openpose_frames(tmp_path, yaws)
    open_page(driver, page_url)
    before = lifts(driver)
    driver.find_element(By.ID, "file").send_keys("\n".join(str(p) for p in paths))
    wait_lift(driver, before)
    before = lifts(driver)
    Select(driver.find_element(By.ID, "temporal")).select_by_value(mode)
    wait_lift(driver, before)
    before = lifts(driver)
    driver.execute_script("const r = document.getElementById('rate'); r.value = '50';"
                          "r.dispatchEvent(new Event('change'));")  # fmt: skip
    wait_lift(driver, before)
    assert page_mode(driver) == mode
    frames = [json.loads(p.read_text())["people"][0]["pose_keypoints_2d"] for p in paths]
    rows = [np.array(f).reshape(-1, 3) for f in frames]
    body = {
        "format": "body25",
        "poses": [{"keypoints": r[:, :2].tolist(), "confidence": r[:, 2].tolist()} for r in rows],
    }
    sent = tracked(body, list(range(len(frames))), mode, 50.0)
    if mode == "off":
        sent = {**sent, "temporal": "off"}
    reply = lift_api(page_url, sent)
    go_to(driver, 8)
    assert_numbers_match(shown_numbers(driver), reply["poses"][8], reply["joints"])
    assert f"{'each pose alone' if mode == 'off' else f'temporal {mode} at 50 fps'}" in text_of(
        driver, "status"
    )
    driver.save_screenshot(str(SHOTS / f"temporal-{mode}.png"))


def test_a_mode_the_service_lacks_is_refused_next_to_the_control(
    driver: Any, lifter: Lifter, tmp_path: Path
) -> None:
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import Select

    paths = openpose_frames(tmp_path, [0.0, 5.0, 10.0])
    with serving(lifter, temporal=False) as url:  # no temporal model: a sequence falls back to off
        open_page(driver, url)
        assert text_of(driver, "model-line").endswith("temporal models: none")
        before = lifts(driver)
        driver.find_element(By.ID, "file").send_keys("\n".join(str(p) for p in paths))
        wait_lift(driver, before)
        assert page_mode(driver) == "off" and "no offline temporal model on this service" in text_of(
            driver, "status"
        )
        Select(driver.find_element(By.ID, "temporal")).select_by_value("causal")
        wait_for(driver, "return document.getElementById('temporal-error').textContent.length > 0")
        assert "this service has no causal temporal model" in text_of(driver, "temporal-error")
        driver.save_screenshot(str(SHOTS / "temporal-missing-model.png"))


def test_several_people_of_one_image_are_each_shown(driver: Any, page_url: str) -> None:
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import Select

    people = [detector_pose("coco17", 10.0), detector_pose("coco17", -30.0) + [700.0, 0.0]]
    triples = [np.concatenate([p, np.full((17, 1), 0.8)], axis=1).ravel().tolist() for p in people]
    results = [{"image_id": 5, "category_id": 1, "score": 0.9, "keypoints": t} for t in triples]
    open_page(driver, page_url)
    before = lifts(driver)
    driver.execute_script("document.getElementById('paste').value = arguments[0]", json.dumps(results))
    driver.find_element(By.ID, "lift-paste").click()
    wait_lift(driver, before)
    assert page_mode(driver) == "off"  # one frame
    body = {
        "format": "coco17",
        "poses": [{"keypoints": p.tolist(), "confidence": [0.8] * 17} for p in people],
    }
    reply = lift_api(page_url, body)
    assert_numbers_match(shown_numbers(driver), reply["poses"][0], reply["joints"])
    Select(driver.find_element(By.ID, "track")).select_by_visible_text("person 1 of each frame")  # --person 1
    assert_numbers_match(shown_numbers(driver), reply["poses"][1], reply["joints"])
    assert text_of(driver, "num-track") == "none, lifted alone"


def test_the_example_list_names_the_users_input_and_an_error_clears_the_last_result(
    driver: Any, page_url: str, tmp_path: Path
) -> None:
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import Select

    def example_shown() -> str:
        return str(Select(driver.find_element(By.ID, "example")).first_selected_option.text)

    open_page(driver, page_url)
    before = lifts(driver)
    Select(driver.find_element(By.ID, "example")).select_by_index(1)
    wait_lift(driver, before)
    example_name = example_shown()
    assert example_name == build_examples()[0]["name"]
    (path,) = openpose_frames(tmp_path, [20.0])
    before = lifts(driver)
    driver.find_element(By.ID, "file").send_keys(str(path))
    wait_lift(driver, before)
    assert example_shown() == f"(your file: {path.name})"  # not the example's name any more
    assert text_of(driver, "num-scale") != "—" and pixels(driver, "view3d")["left"]["count"] > 300
    driver.save_screenshot(str(SHOTS / "your-file.png"))

    driver.execute_script("document.getElementById('paste').value = '[[1, 2], [3, 4]]'")
    driver.find_element(By.ID, "lift-paste").click()
    wait_for(driver, "return document.getElementById('paste-error').textContent.length > 0")
    assert example_shown() == "(your pasted input)"
    assert driver.execute_script("return document.getElementById('file').value") == ""
    assert all(text_of(driver, f"num-{k}") == "—" for k in shown_numbers(driver))
    flat, solid = pixels(driver, "view2d"), pixels(driver, "view3d")
    assert flat["drawn"] == 0 and solid["left"]["count"] == 0 and solid["right"]["count"] == 0
    assert not driver.find_element(By.ID, "player").is_displayed()
    driver.save_screenshot(str(SHOTS / "error-clears-result.png"))
    before = lifts(driver)
    driver.execute_script("const f = document.getElementById('format'); f.value = 'coco17';"
                          "f.dispatchEvent(new Event('change'));")  # fmt: skip
    time.sleep(0.5)  # the last input is the rejected paste (refused again), not the earlier file
    assert lifts(driver) == before and text_of(driver, "num-scale") == "—"
    driver.execute_script("const f = document.getElementById('format'); f.value = '';")

    before = lifts(driver)
    Select(driver.find_element(By.ID, "example")).select_by_index(1)
    wait_lift(driver, before)
    assert example_shown() == example_name
    assert driver.execute_script("return document.getElementById('file').value") == ""


def test_mediapipe_rows_with_a_request_or_a_pose_image_size_are_lifted_and_drawn_in_pixels(
    driver: Any, page_url: str
) -> None:
    """MediaPipe [x, y, z, visibility] rows normalised to [0, 1]: with the body's image_size (as curl
    sends it) or the pose's own, the page gets the API's answer and draws the 2D input where the same
    pose in pixels is drawn (not shrunk into the top-left corner)."""
    from selenium.webdriver.common.by import By

    size = [1000.0, 1000.0]
    landmarks, found = from_model_joints(FORMATS["mediapipe33"], project(POSE_3D, 30.0)[None])
    pixels_pose = np.where(found[0][:, None], landmarks[0], landmarks[0, 0]).round(1)  # the face at the nose
    rows = [[x / size[0], y / size[1], 0.0, 0.9] for x, y in pixels_pose.tolist()]
    bodies = {
        "request": {"poses": [{"keypoints": rows}], "format": "mediapipe33", "image_size": size},
        "pose": {"poses": [{"keypoints": rows, "image_size": size}], "format": "mediapipe33"},
        "pixels": {
            "poses": [{"keypoints": [[x, y, 0.9] for x, y in pixels_pose.tolist()]}],
            "format": "mediapipe33",
        },
    }
    open_page(driver, page_url)
    drawn = {}
    for name, body in bodies.items():
        before = lifts(driver)
        driver.execute_script("document.getElementById('paste').value = arguments[0]", json.dumps(body))
        driver.find_element(By.ID, "lift-paste").click()
        wait_lift(driver, before)
        assert text_of(driver, "paste-error") == ""
        assert_numbers_match(
            shown_numbers(driver), lift_api(page_url, body), lift_api(page_url, body)["joints"]
        )
        drawn[name] = pixels(driver, "view2d")
        driver.save_screenshot(str(SHOTS / f"mediapipe-image-size-{name}.png"))
    for name in ("request", "pose"):
        assert drawn[name]["box"] == drawn["pixels"]["box"], name
        assert drawn[name]["left"]["count"] == pytest.approx(drawn["pixels"]["left"]["count"], rel=0.02)
    x0, y0, x1, y1 = drawn["pixels"]["box"]
    assert x1 - x0 > 100 and y1 - y0 > 100  # a person, not a dot in a corner


def test_camera_intrinsics_show_where_the_person_stands_and_the_root_trajectory(
    driver: Any, page_url: str, tmp_path: Path
) -> None:
    """A person walking to the image right: with the intrinsics and a height typed in, each frame shows
    the API's root_camera_m, and the trajectory seen from above marks the frame's root, which moves
    right as the player steps; a bad value is named next to its field."""
    from selenium.webdriver.common.by import By

    paths = []
    for i in range(8):  # the test pose walking right (detector_pose: body25 at 4.5 m)
        body = detector_pose("body25", 10.0) + [25.0 * i, 0.0]
        flat = np.concatenate([body, np.full((len(body), 1), 0.9)], axis=1).ravel().tolist()
        paths.append(tmp_path / f"walk_{i:012d}_keypoints.json")
        paths[-1].write_text(json.dumps({"version": 1.3, "people": [{"pose_keypoints_2d": flat}]}))
    open_page(driver, page_url)
    driver.execute_script("document.getElementById('intrinsics').value = '1145, 1145, 512, 515';"
                          "document.getElementById('height').value = '1.7';")  # fmt: skip
    before = lifts(driver)
    driver.find_element(By.ID, "file").send_keys("\n".join(str(p) for p in paths))
    wait_lift(driver, before)
    assert driver.execute_script("return document.getElementById('trajectory-figure').hidden") is False
    rows = [
        np.array(json.loads(p.read_text())["people"][0]["pose_keypoints_2d"]).reshape(-1, 3) for p in paths
    ]
    camera = {"focal_px": [1145.0, 1145.0], "principal_point_px": [512.0, 515.0]}
    poses = [{"keypoints": r[:, :2].tolist(), "confidence": r[:, 2].tolist()} for r in rows]
    body = {"format": "body25", "intrinsics": camera, "person_height_m": 1.7, "poses": poses}
    reply = lift_api(page_url, tracked(body, list(range(8)), page_mode(driver), 30.0))
    markers = []
    for k in (0, 7):
        go_to(driver, k)
        root = reply["poses"][k]["root_camera_m"]
        assert text_of(driver, "num-root") == f"{', '.join(f'{v:.3f}' for v in root)} m (height: given)"
        markers.append(pixels(driver, "trajectory")["imputed"])
        if k == 0:
            driver.save_screenshot(str(SHOTS / "trajectory.png"))
    assert markers[0]["count"] > 60 and markers[1]["count"] > 60, markers
    assert markers[1]["x"] - markers[0]["x"] > 40  # the current root moved right on the top view
    assert reply["poses"][7]["root_camera_m"][0] - reply["poses"][0]["root_camera_m"][0] > 0.5
    driver.find_element(By.ID, "trajectory").screenshot(str(SHOTS / "trajectory-top-view.png"))
    before = lifts(driver)
    driver.execute_script("const h = document.getElementById('height'); h.value = '1750';"
                          "h.dispatchEvent(new Event('change'));")  # fmt: skip
    wait_for(driver, "return document.getElementById('height-error').textContent.length > 0")
    assert "millimetres? divide by 1000" in text_of(driver, "height-error")
    driver.execute_script("const i = document.getElementById('intrinsics'); i.value = '1145, 512';"
                          "i.dispatchEvent(new Event('change'));")  # fmt: skip
    wait_for(driver, "return document.getElementById('intrinsics-error').textContent.length > 0")
    assert "expected fx, fy, cx, cy" in text_of(driver, "intrinsics-error") and lifts(driver) == before
    driver.save_screenshot(str(SHOTS / "trajectory-errors.png"))


# ---- the live mode: a fake camera fed from a real clip ----


def write_y4m(clip: Path, out: Path, repeat: int) -> int:
    """The clip as a raw 4:2:0 .y4m at 30 fps (each frame shown `repeat` times), Chromium's fake camera."""
    import av

    with av.open(str(clip)) as container:
        frames = [f.to_ndarray(format="yuv420p") for f in container.decode(video=0)]
    height, width = frames[0].shape[0] * 2 // 3, frames[0].shape[1]
    with out.open("wb") as f:
        f.write(f"YUV4MPEG2 W{width} H{height} F30:1 Ip A1:1 C420jpeg\n".encode())
        for frame in frames:
            for _ in range(repeat):
                f.write(b"FRAME\n" + frame.tobytes())
    return len(frames) * repeat


def test_live_mode_lifts_the_fake_camera_causally_and_draws_the_person(
    lifter: Lifter, page_url: str, tmp_path: Path
) -> None:
    if shutil.which("chromium") is None or shutil.which("chromedriver") is None:
        pytest.skip("needs Debian's chromium and chromium-driver")
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service
    from selenium.webdriver.common.by import By

    clip = tmp_path / "clip.y4m"
    street = Path(__file__).resolve().parents[1] / "fixtures" / "video" / "street640.mp4"
    assert write_y4m(street, clip, 6) == 30
    SHOTS.mkdir(parents=True, exist_ok=True)
    options = webdriver.ChromeOptions()
    options.binary_location = shutil.which("chromium")
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                "--window-size=1560,1250", "--force-device-scale-factor=1",
                "--use-fake-device-for-media-stream", "--use-fake-ui-for-media-stream",
                f"--use-file-for-fake-video-capture={clip}"):  # fmt: skip
        options.add_argument(arg)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    chromedriver = Service(executable_path=shutil.which("chromedriver"))
    driver = webdriver.Chrome(options=options, service=chromedriver)
    try:
        open_page(driver, page_url)
        driver.find_element(By.ID, "live-camera").click()
        try:
            stopped = "document.getElementById('live-status').textContent.startsWith('live mode stopped')"
            wait_for(
                driver, f"return Number(document.body.dataset.liveDrawn || 0) >= 40 || {stopped}", timeout=90
            )
        finally:
            print(driver.find_element(By.ID, "live-status").text, driver.get_log("browser"))
        latency = json.loads(driver.execute_script("return document.body.dataset.liveLatency"))
        status = driver.find_element(By.ID, "live-status").text
        print(f"live latency: {latency}; {status}")
        assert "p95" in status and latency["n"] >= 40 and 0 < latency["p50"] <= latency["p95"]
        driver.execute_script("document.getElementById('live').scrollIntoView()")
        driver.find_element(By.ID, "live").screenshot(str(SHOTS / "live-camera.png"))
        driver.find_element(By.ID, "live3d").screenshot(str(SHOTS / "live-3d.png"))
        # the 3D canvas holds a drawn skeleton (opaque pixels), not an empty view
        drawn = driver.execute_script(
            "return document.getElementById('live3d').getContext('2d')"
            ".getImageData(0, 0, 480, 480).data.filter((v, i) => i % 4 === 3 && v > 0).length"
        )
        assert drawn > 1000
        # the vendored WebAssembly prints TensorFlow Lite's log lines to stderr: Chromium logs them as errors
        tflite_info = '"INFO: Created TensorFlow Lite'
        log = driver.get_log("browser")
        errors = [e for e in log if e["level"] == "SEVERE" and tflite_info not in e["message"]]
        assert not errors, errors
        driver.find_element(By.ID, "live-stop").click()
        assert driver.find_element(By.ID, "live-status").text == "stopped"
    finally:
        driver.quit()
