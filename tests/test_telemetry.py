"""onnxruntime's usage telemetry (on by default on Linux since 1.29) is turned off by the code, not
only by `make` and the Dockerfile (issue 31): whatever makes a session first, `repnet serve`,
`repnet lift --local`, training, export or `repnet adapt`, has turned it off by then."""

from __future__ import annotations

import subprocess
import sys

import pytest

CODE = """
import onnxruntime as ort
calls = []
ort.disable_telemetry_events = lambda: calls.append(1)
import {module}
assert calls, "{module} left onnxruntime's telemetry on"
"""


@pytest.mark.parametrize(
    "module",
    [
        "repnet.runtime.lifter",
        "repnet.runtime.detector",
        "repnet.cli.local",
        "repnet.train.export",
        "repnet.train.adapt",
        "repnet.train.evaluate",
        "repnet.train.rebase",
    ],
)
def test_importing_what_makes_a_session_turns_telemetry_off(module: str) -> None:
    done = subprocess.run(
        [sys.executable, "-c", CODE.format(module=module)], capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr[-2000:]
