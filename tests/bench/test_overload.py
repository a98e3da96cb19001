"""bench.overload on a tiny setting: it runs against a started server and writes its figures."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from bench.overload import main


def test_overload_reports_the_status_mix_latencies_and_readiness(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "overload.json"
    assert main(["--concurrency", "8", "--duration", "1.5", "--ramp", "0.2", "--json", str(out)]) == 0
    found = json.loads(out.read_text())
    assert found["statuses"].get("200", 0) > 0 and found["requests"] == sum(found["statuses"].values())
    assert set(found["latency_ms"]["200"]) == {"p50", "p90", "p99", "mean"}
    assert found["readyz"]["probes"] >= 1 and found["readyz"]["failed"] == 0
    printed = capsys.readouterr().out
    assert "status mix:" in printed and "/readyz on a fresh connection" in printed
