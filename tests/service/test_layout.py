"""The layout of service/: imports point one way (no circle, not even type-level), modules stay small."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SERVICE = Path(__file__).resolve().parents[2] / "service"
MODULES = {p.stem: p for p in SERVICE.glob("*.py")}
MAX_LINES = 350
# Modules that must not know a wire format, a reply, or the server around them.
MUST_NOT_IMPORT = {
    "keypoints": {"lookalike", "replies", "lifter", "engine", "grpc", "fastapi"},
    "lifter": {"replies", "keypoints", "engine", "grpc", "fastapi"},
    "engine": {"replies", "lookalike", "geometry", "grpc", "fastapi", "http_api", "grpc_api"},
    "replies": {"engine", "grpc", "fastapi"},
    "stream": {"grpc", "grpc_api", "fastapi"},
    "formats": {"keypoints", "lookalike", "replies"},
    "cli": {"http_api", "grpc_api", "http_middleware"},  # --local lifts with the core, not an adapter
    "cli_lift": {"http_api", "http_temporal", "grpc_api", "http_middleware"},
    "local_lift": {"http_api", "http_temporal", "grpc_api", "http_middleware", "fastapi", "grpc"},
    # what the clients share: no server, no onnxruntime
    "contract": {"onnxruntime", "grpc", "fastapi", "httpx"},
    "chunks": {"onnxruntime", "grpc", "fastapi", "httpx"},
    "lift_result": {"onnxruntime", "grpc", "fastapi", "httpx"},
}


def imports(path: Path) -> set[str]:
    """Every module `path` imports anywhere (top level, in functions, under TYPE_CHECKING): service
    modules by their own name, others by their top-level package."""
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        names = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
        for name in names:
            parts = name.split(".")
            if parts[0] == "service" and len(parts) > 1 and parts[1] in MODULES:
                found.add(parts[1])
            elif parts[0] != "service":
                found.add(parts[0])
    return found - {path.stem}


GRAPH = {name: imports(path) & set(MODULES) for name, path in MODULES.items()}


def test_service_imports_have_no_circle() -> None:
    def visit(name: str, trail: tuple[str, ...]) -> None:
        for dep in sorted(GRAPH[name]):
            assert dep not in trail, f"import circle: {' -> '.join((*trail, dep))}"
            visit(dep, (*trail, dep))

    for name in MODULES:
        visit(name, (name,))


@pytest.mark.parametrize("name", sorted(MUST_NOT_IMPORT))
def test_core_modules_do_not_import_outer_ones(name: str) -> None:
    assert not imports(MODULES[name]) & MUST_NOT_IMPORT[name]


def test_service_never_imports_training() -> None:
    assert [name for name, path in MODULES.items() if "training" in imports(path)] == []


def test_modules_stay_under_the_size_limit() -> None:
    sizes = {name: len(path.read_text().splitlines()) for name, path in MODULES.items()}
    assert {name: n for name, n in sizes.items() if n > MAX_LINES} == {}
