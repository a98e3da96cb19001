"""The house: the package's rooms keep their contracts (import-linter, pyproject [tool.importlinter]),
no module grows past the line cap once formatted, and nothing imports the folders by their own names."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
MAX_LINES = 350  # formatted: `# fmt: skip` and `# fmt: off` do not count as packing
# Modules allowed past the cap, each with why (none today).
OVER_THE_CAP: dict[str, str] = {}
JS_MAX_LINES = 420  # as written (test_the_pages_scripts_stay_small)
PYTHON_ROOMS = ("service", "training", "bench")
SKIP = re.compile(r"\s*# fmt: (skip|off|on)\b.*$", re.M)


def layout(tmp: Path) -> Path:
    """A tree where service/ is repnet and training/ is repnet.train, as the wheel installs them."""
    package = tmp / "repnet"
    package.mkdir()
    for entry in (ROOT / "service").iterdir():
        (package / entry.name).symlink_to(entry)
    (package / "train").symlink_to(ROOT / "training")
    return tmp


def test_the_rooms_keep_their_contracts(tmp_path: Path) -> None:
    """import-linter's contracts, all kept (the same check as `make contracts` and CI's step)."""
    env = {**os.environ, "PYTHONPATH": str(layout(tmp_path))}
    command = "import sys; from importlinter.cli import lint_imports_command as c; sys.exit(c())"
    run = subprocess.run(
        [sys.executable, "-c", command, "--no-cache", str(ROOT / "pyproject.toml")],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-2000:]
    assert "0 broken" in run.stdout and "kept" in run.stdout


def formatted_lines(path: Path) -> int:
    """The lines of a module as ruff formats it with its `fmt: skip` / `fmt: off` markers removed."""
    text = SKIP.sub("", path.read_text())
    run = subprocess.run(
        [sys.executable, "-m", "ruff", "format", "--stdin-filename", str(path), "-"],
        input=text, capture_output=True, text=True, cwd=ROOT, check=True,
    )  # fmt: skip
    return len(run.stdout.splitlines())


def python_modules() -> list[Path]:
    return sorted(p for room in PYTHON_ROOMS for p in (ROOT / room).rglob("*.py") if "_proto" not in p.parts)


def test_no_module_is_over_the_cap_once_formatted() -> None:
    over = {}
    for path in python_modules():
        name = str(path.relative_to(ROOT))
        if name not in OVER_THE_CAP and (lines := formatted_lines(path)) > MAX_LINES:
            over[name] = lines
    assert over == {}


def test_the_pages_scripts_stay_small() -> None:
    """The page's JS is held to its lines as written, not formatted ones: the project carries no JS
    formatter (its toolchain is pip's; CI installs no Node packages). Its cap is JS_MAX_LINES until
    the page is split further (page.js is the largest)."""
    for path in sorted((ROOT / "service" / "server" / "static").glob("*.js")):
        assert len(path.read_text().splitlines()) <= JS_MAX_LINES, path.name


@pytest.mark.parametrize("old", ["service", "training"])
def test_nothing_imports_the_folders_by_their_own_names(old: str) -> None:
    """service/ is only ever repnet and training/ repnet.train: an `import service...` would load a
    second copy of the modules beside the package's."""
    pattern = re.compile(rf"^\s*(from {old}(\.| import)|import {old}\b)", re.M)
    found = [
        str(p.relative_to(ROOT))
        for room in (*PYTHON_ROOMS, "tests", "proto")
        for p in (ROOT / room).rglob("*.py")
        if "_proto" not in p.parts and pattern.search(p.read_text())
    ]
    assert found == []
