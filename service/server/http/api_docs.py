"""GET /docs: Swagger UI on the OpenAPI document, from files this package serves (no CDN).

FastAPI's own /docs loads Swagger UI from a CDN, so on a machine without internet the page is
blank, and its inline script needs a CSP that allows inline code. Here the bundle and stylesheet
come from the fastapi-offline package (which ships swagger-ui-dist's files: MIT, Swagger UI
itself Apache-2.0), the start-up script is a file of ours, and every file is read once at start
and served from memory under the web page's Content-Security-Policy: this origin only.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

from fastapi import FastAPI
from fastapi.responses import Response

from repnet.server.http.page import HEADERS

# Every file /docs may load, with where it comes from and its media type; anything else is a 404.
ASSETS = {
    "swagger-ui-bundle.js": ("fastapi_offline", "text/javascript; charset=utf-8"),
    "swagger-ui.css": ("fastapi_offline", "text/css; charset=utf-8"),
    "docs.js": ("service", "text/javascript; charset=utf-8"),
}
DOCS_DIR = Path(__file__).resolve().parents[1] / "apidocs"


def _read(name: str, package: str) -> bytes:
    if package == "service":
        return (DOCS_DIR / name).read_bytes()
    return resources.files(package).joinpath("static").joinpath(name).read_bytes()


def add_docs(app: FastAPI, path: str = "/docs") -> None:
    """Serve Swagger UI at GET `path` and its files at GET `path`/<name> (the app must have been made
    with docs_url=None, and keeps its openapi_url)."""
    index = (DOCS_DIR / "index.html").read_bytes()
    assets = {name: _read(name, package) for name, (package, _) in ASSETS.items()}

    @app.api_route(path, methods=["GET", "HEAD"], include_in_schema=False)
    async def docs() -> Response:
        return Response(index, media_type="text/html; charset=utf-8", headers=HEADERS)

    @app.get(path + "/{name}", include_in_schema=False)
    async def asset(name: str) -> Response:
        if name not in assets:
            return Response(b"not found", status_code=404, media_type="text/plain", headers=HEADERS)
        return Response(assets[name], media_type=ASSETS[name][1], headers=HEADERS)
