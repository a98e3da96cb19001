"""The web page at GET /: how it is served, and the page itself in a real browser (Debian's chromium
through chromium-driver) against a running service. Screenshots go to runs/page/."""

from __future__ import annotations

import contextlib
import json
import math
import os
import re
import shutil
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient

from service.app import build_app
from service.config import Settings
from service.engine import Engine
from service.lifter import Lifter
from service.metrics import Metrics
from service.page import ASSETS, CSP, STATIC_DIR
from tests.conftest import load_model
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
    engine: Engine, metrics: Metrics, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("REPNET_UI", "false")
    assert Settings().ui is False
    with TestClient(build_app(engine, metrics, Settings())) as client:
        assert client.get("/").status_code == 404 and client.get("/ui/page.js").status_code == 404
        assert client.get("/healthz").status_code == 200


def test_the_bundle_names_no_other_origin_and_no_inline_code() -> None:
    files = {p.name: p.read_text() for p in STATIC_DIR.iterdir()}
    assert set(files) == {*ASSETS, "index.html"}
    for name, text in files.items():
        text = text.replace('xmlns="http://www.w3.org/2000/svg"', "")  # a name, never fetched
        assert not re.search(r"(https?:)?//[a-z0-9.-]+\.[a-z]{2,}", text, re.I), name
    html = files["index.html"]
    assert re.findall(r"<script[^>]*>", html) == ['<script type="module" src="/ui/page.js">']
    assert not re.search(r"\son[a-z]+=", html) and "style=" not in html
    scripts = "".join(files[n] for n in ASSETS if n.endswith(".js"))
    assert "innerHTML" not in scripts and "insertAdjacentHTML" not in scripts and "eval(" not in scripts
    assert set(re.findall(r"fetch\(\"([^\"]+)\"", scripts)) == {"/lift", "/v1/model", "/ui/examples.json"}


def test_bundled_examples_are_current() -> None:
    """Regenerate with python -m tests.service.page_examples."""
    assert json.loads(EXAMPLES_PATH.read_text()) == json.loads(json.dumps(build_examples()))


# ---- in the browser ----


@contextlib.contextmanager
def serving(lifter: Lifter) -> Iterator[str]:
    """The service as `python -m service` runs it, with a small body limit for the upload test."""
    from service.app import build_service

    settings = Settings(host="127.0.0.1", http_port=0, grpc_port=0, intra_op_threads=1,
                        shutdown_grace_s=1, max_body_bytes=BODY_LIMIT)  # fmt: skip
    service = build_service(settings, lifter)
    thread = threading.Thread(target=service.run, name="page-service", daemon=True)
    thread.start()
    deadline = time.monotonic() + 20
    while not service.http.started:
        if time.monotonic() > deadline or not thread.is_alive():
            raise RuntimeError("the service did not start")
        time.sleep(0.02)
    try:
        yield f"http://127.0.0.1:{service.http.servers[0].sockets[0].getsockname()[1]}"
    finally:
        service.begin_shutdown()
        thread.join(timeout=15)


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


def wait_lift(driver: Any, before: int) -> None:
    wait_for(driver, f"return Number(document.body.dataset.lifts || 0) > {before}")


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
    assert text_of(driver, "frame-label") == f"frame 1 / {len(yaws)}"
    body = {"format": "body25", "poses": [json.loads(p.read_text())["people"][0] for p in paths]}
    body["poses"] = [
        {"keypoints": np.array(p["pose_keypoints_2d"]).reshape(-1, 3)[:, :2].tolist(),
         "confidence": np.array(p["pose_keypoints_2d"]).reshape(-1, 3)[:, 2].tolist()}
        for p in body["poses"]
    ]  # fmt: skip
    reply = lift_api(page_url, body)
    assert_numbers_match(shown_numbers(driver), reply["poses"][0], reply["joints"])
    first = pixels(driver, "view3d")["hash"]
    driver.find_element(By.ID, "next").click()
    assert text_of(driver, "frame-label") == f"frame 2 / {len(yaws)}"
    assert_numbers_match(shown_numbers(driver), reply["poses"][1], reply["joints"])
    assert pixels(driver, "view3d")["hash"] != first
    driver.execute_script("const s = document.getElementById('frame'); s.value = '6';"
                          "s.dispatchEvent(new Event('input'));")  # fmt: skip
    assert text_of(driver, "frame-label") == f"frame 7 / {len(yaws)}"
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
    reply = lift_api(page_url, body)
    driver.find_element(By.ID, "next").click()
    assert text_of(driver, "frame-label") == "frame 2 / 3"
    assert_numbers_match(shown_numbers(driver), reply["poses"][1], reply["joints"])
    assert "left_wrist" in text_of(driver, "num-imputed")


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
        f"file big.json has {big.stat().st_size} bytes, more than the {BODY_LIMIT}-byte limit of a /lift body"
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
        assert "plausibility: given" in text_of(driver, "model-line")
        before = lifts(driver)
        Select(driver.find_element(By.ID, "example")).select_by_index(4)  # the 36-frame sequence
        wait_lift(driver, before)
        frames = build_examples()[3]["data"]
        body = {"format": "body25", "poses": [
            {"keypoints": np.array(f["people"][0]["pose_keypoints_2d"]).reshape(-1, 3)[:, :2].tolist()}
            for f in frames]}  # fmt: skip
        reply = lift_api(url, body)
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

    from service.cli import EXIT_OK, main

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
