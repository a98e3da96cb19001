"""Point 3: on a workstation the service binds 127.0.0.1; the container image binds 0.0.0.0.

On main Settings bound 0.0.0.0 by default, so `make serve` or `repnet serve` on a laptop served
every network it was on.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml

from repnet.cli.main import main as repnet
from repnet.server.app import parse_settings
from repnet.server.config import Settings

ROOT = Path(__file__).resolve().parents[2]


def test_make_serve_and_repnet_serve_bind_loopback(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.delenv("REPNET_HOST", raising=False)
    assert Settings().host == "127.0.0.1"
    assert parse_settings([]).host == "127.0.0.1"  # `python -m repnet serve`, what `make serve` runs
    with pytest.raises(SystemExit):
        repnet(["serve", "--help"])  # `repnet serve` is the same parser, whose help gives the default
    assert "(default: 127.0.0.1)" in " ".join(capsys.readouterr().out.split())
    makefile = (ROOT / "Makefile").read_text()
    assert re.search(r"^serve: .*\n\t\$\(PY\) -m repnet serve$", makefile, re.M)  # no --host of its own


def test_the_image_and_the_deployment_bind_every_address() -> None:
    assert "REPNET_HOST=0.0.0.0" in (ROOT / "Dockerfile").read_text()
    deployment = yaml.safe_load((ROOT / "deploy/k8s/base/deployment.yaml").read_text())
    (container,) = deployment["spec"]["template"]["spec"]["containers"]
    assert {"name": "REPNET_HOST", "value": "0.0.0.0"} in container["env"]
