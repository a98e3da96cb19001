"""/docs works without internet: Swagger UI comes from this service, under the page's CSP.

On main, FastAPI's /docs loaded Swagger UI's script and stylesheet from a CDN (and its favicon from
fastapi.tiangolo.com), so on a machine without internet the page stayed blank. Headless chromium
loads /docs here and every request it makes must go to the service's own origin; a screenshot goes
to runs/docs/.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import pytest
from fastapi.testclient import TestClient

from repnet.runtime.lifter import Lifter
from repnet.server.http.api_docs import ASSETS
from repnet.server.http.page import CSP
from tests.service.test_page import driver, serving

__all__ = ["driver"]  # the module's headless chromium fixture, shared with the page's tests

SHOTS = Path(__file__).resolve().parents[2] / "runs" / "docs"


def test_docs_and_its_files_are_served_from_the_service_under_the_page_csp(client: TestClient) -> None:
    page = client.get("/docs")
    assert page.status_code == 200 and page.headers["content-security-policy"] == CSP
    assert "cdn" not in page.text and "<script>" not in page.text  # no inline code, no CDN
    for name, (_, media_type) in ASSETS.items():
        asset = client.get(f"/docs/{name}")
        assert asset.status_code == 200 and asset.headers["content-type"] == media_type
        assert asset.headers["content-security-policy"] == CSP and len(asset.content) > 100
    assert client.get("/docs/..%2Fconfig.py").status_code == 404
    assert client.get("/openapi.json").status_code == 200


@pytest.fixture(scope="module")
def docs_url(lifter: Lifter) -> Iterator[str]:
    with serving(lifter) as url:
        yield url + "/docs"


def test_docs_page_makes_only_same_origin_requests_in_chromium(docs_url: str, driver: Any) -> None:
    driver.get_log("performance")  # drop what earlier pages logged
    driver.get_log("browser")
    driver.get(docs_url)
    deadline = time.monotonic() + 30
    while not driver.execute_script("return document.querySelectorAll('.opblock').length"):
        assert time.monotonic() < deadline, "Swagger UI did not render the operations"
        time.sleep(0.2)
    time.sleep(1.0)  # late requests (fonts, images) have time to start
    SHOTS.mkdir(parents=True, exist_ok=True)
    driver.save_screenshot(str(SHOTS / "docs.png"))
    requests = []
    for entry in driver.get_log("performance"):
        message = json.loads(entry["message"])["message"]
        if message["method"] == "Network.requestWillBeSent":
            requests.append(message["params"]["request"]["url"])
    origin = urlsplit(docs_url)[:2]
    assert any(url.endswith("/openapi.json") for url in requests), requests
    assert any(url.endswith("/docs/swagger-ui-bundle.js") for url in requests), requests
    foreign = [u for u in requests if urlsplit(u)[:2] != origin and not u.startswith("data:")]
    assert not foreign, foreign
    refused = [e["message"] for e in driver.get_log("browser") if "Content Security Policy" in e["message"]]
    assert not refused, refused
    operations = driver.execute_script(
        "return [...document.querySelectorAll('.opblock-summary-path')].map(e => e.textContent)"
    )
    assert "/lift" in operations and "/readyz" in operations
