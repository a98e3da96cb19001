"""`make container-test` as a fresh clone runs it: the venv's Python for the host-side smoke checks."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.skipif(shutil.which("make") is None, reason="make is not installed")


def dry_run(*variables: str) -> list[str]:
    """The commands `make container-test` would run, in order (make -n runs none of them). Under
    `make test` (as in CI) the outer make's variables are dropped, so this is a top-level make that
    prints no "make[1]: Entering directory" lines."""
    outer = ("MAKEFLAGS", "MFLAGS", "MAKELEVEL", "MAKEOVERRIDES")
    env = {k: v for k, v in os.environ.items() if k not in outer}
    done = subprocess.run(["make", "--no-print-directory", "-n", "container-test", *variables], cwd=ROOT,
                          capture_output=True, text=True, check=True, env=env)  # fmt: skip
    return done.stdout.strip().splitlines()


def script_python(line: str) -> str:
    found = re.fullmatch(r"PYTHON=(\S+) bash deploy/test-container\.sh", line)
    assert found, f"container-test must pass PYTHON to the script, runs: {line}"
    return found.group(1)


def test_container_test_creates_the_venv_and_runs_the_script_with_its_python(tmp_path: Path) -> None:
    venv = tmp_path / "fresh-venv"  # as in a fresh clone: no venv yet
    commands = dry_run(f"VENV={venv}")
    assert any(f"-m venv {venv}" in c for c in commands), commands  # the venv is made first
    # with the service in it (and the `cli` extra: `repnet plot` works after `make serve`)
    assert any("pip install" in c and "-e '.[server,cli]'" in c for c in commands), commands
    assert script_python(commands[-1]) == str(venv / "bin" / "python")


def test_container_test_without_a_venv_uses_the_given_interpreter_and_it_has_the_smoke_deps() -> None:
    python = script_python(dry_run("VENV=", f"PYTHON3={sys.executable}")[-1])
    assert python == sys.executable
    subprocess.run([python, "-c", "import grpc, grpc_health, httpx"], check=True)


def test_the_script_refuses_a_python_without_the_smoke_deps_before_doing_anything(tmp_path: Path) -> None:
    fake = tmp_path / "python"
    fake.write_text("#!/bin/sh\nexit 1\n")
    fake.chmod(0o755)
    env = {"PATH": "/usr/bin:/bin", "PYTHON": str(fake)}
    script = str(ROOT / "deploy" / "test-container.sh")
    done = subprocess.run(["bash", script], capture_output=True, text=True, env=env, timeout=60)
    assert done.returncode == 1
    assert "cannot import grpc, grpc_health and httpx" in done.stdout + done.stderr
    assert "make container-test" in done.stdout + done.stderr
