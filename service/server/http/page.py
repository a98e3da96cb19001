"""The web page at GET /: a static bundle (service/static/) that lifts keypoints through /lift and draws them.

The page is plain files, no build step: index.html, its stylesheet and ES modules, and the bundled
example poses. They are read once at start-up and served from memory under fixed names, so no
request path reaches the file system. A Content-Security-Policy keeps the page to its own origin:
scripts and styles from these files only (no inline code), requests to this service only.
"""

from __future__ import annotations

from pathlib import Path

from fastapi import FastAPI
from fastapi.responses import Response

STATIC_DIR = Path(__file__).resolve().parents[1] / "static"
# Every file the page may load, with its media type; anything else under /ui/ is a 404.
ASSETS = {
    "page.css": "text/css; charset=utf-8",
    "page.js": "text/javascript; charset=utf-8",
    "parse.js": "text/javascript; charset=utf-8",
    "detectors.js": "text/javascript; charset=utf-8",
    "lift.js": "text/javascript; charset=utf-8",
    "notes.js": "text/javascript; charset=utf-8",
    "track.js": "text/javascript; charset=utf-8",
    "view.js": "text/javascript; charset=utf-8",
    "trajectory.js": "text/javascript; charset=utf-8",
    "examples.json": "application/json",
    "icon.svg": "image/svg+xml",
    "live.js": "text/javascript; charset=utf-8",
}
# The live mode's 2D detector: the npm package @mediapipe/tasks-vision as published (its ES module and
# SIMD WebAssembly build) and a lite pose landmarker model (vendor/mediapipe/README.md says whence).
# Served as they are, under the same allow-list.
VENDOR = "vendor/mediapipe/"
ASSETS |= {
    VENDOR + "vision_bundle.mjs": "text/javascript; charset=utf-8",
    VENDOR + "vision_wasm_internal.js": "text/javascript; charset=utf-8",
    VENDOR + "vision_wasm_internal.wasm": "application/wasm",
    VENDOR + "pose_landmarker_lite.task": "application/octet-stream",
}
# 'wasm-unsafe-eval' lets the page compile WebAssembly (the vendored detector's), and nothing else:
# no eval, no inline script; the .wasm and the model must still come from this origin (connect-src
# 'self'), and the detector's loader is a script of this origin too (script-src 'self'). It needs no
# worker and no blob: script.
# media-src blob: plays the video file the user picks for the live mode (an object URL of it).
CSP = (
    "default-src 'none'; script-src 'self' 'wasm-unsafe-eval'; media-src blob:; style-src 'self'; "
    "img-src 'self'; connect-src 'self'; "
    "base-uri 'none'; form-action 'none'; frame-ancestors 'none'"
)
HEADERS = {
    "Content-Security-Policy": CSP,
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
    "Cache-Control": "no-cache",  # a new release's page must not mix with the last one's scripts
}


def add_page(app: FastAPI) -> None:
    """Serve the page at GET / and its files at GET /ui/<name> (left out of the OpenAPI schema)."""
    index = (STATIC_DIR / "index.html").read_bytes()
    assets = {name: (STATIC_DIR / name).read_bytes() for name in ASSETS}

    @app.api_route("/", methods=["GET", "HEAD"], include_in_schema=False)
    async def page() -> Response:
        return Response(index, media_type="text/html; charset=utf-8", headers=HEADERS)

    @app.get("/ui/{name:path}", include_in_schema=False)
    async def asset(name: str) -> Response:
        if name not in assets:
            return Response(b"not found", status_code=404, media_type="text/plain", headers=HEADERS)
        return Response(assets[name], media_type=ASSETS[name], headers=HEADERS)
