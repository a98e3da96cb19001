"""schemathesis against the running service's OpenAPI spec: no 5xx, every answer matches the schema."""

from __future__ import annotations

import re
from typing import Any

import httpx
import pytest
import schemathesis
from hypothesis import HealthCheck, settings
from schemathesis import checks

from bench.server import ServiceProcess


@pytest.fixture(scope="module")
def api_schema(service_process: ServiceProcess) -> schemathesis.BaseSchema:
    return schemathesis.openapi.from_url(f"{service_process.url}/openapi.json")


schema = schemathesis.pytest.from_fixture("api_schema")


@schema.parametrize()
@settings(max_examples=50, deadline=None, database=None, suppress_health_check=list(HealthCheck))
def test_api_answers_every_generated_request_within_its_schema(case: schemathesis.Case[Any]) -> None:
    # The schema cannot say everything the service checks (joints per format, visible joints,
    # coordinate range): schema-valid requests may get a documented 422, so that check is off.
    excluded = [checks.positive_data_acceptance]
    body = case.body if isinstance(case.body, dict) else {}
    report = body.get("invalid_poses") == "report"
    if report:  # documented: a pose the schema refuses is answered null with its errors, not 422
        excluded.append(checks.negative_data_rejection)
    response = case.call_and_validate(excluded_checks=excluded)
    if report and response.status_code == 200:
        answer = response.json()
        unlifted = {i for i, pose in enumerate(answer["poses"]) if pose is None}
        assert unlifted == {e["pose"] for e in answer.get("errors", [])}, answer.get("errors")


def test_the_fuzzing_reached_both_answers_and_no_server_error(service_process: ServiceProcess) -> None:
    """Runs after the fuzz test: generated /lift requests were both lifted and rejected, never a 5xx."""
    text = httpx.get(f"{service_process.url}/metrics", timeout=5).text
    counts = {
        outcome: float(value)
        for outcome, value in re.findall(
            r'repnet_requests_total\{method="Lift",outcome="(\w+)",transport="http"\} (\S+)', text
        )
    }
    assert counts.get("ok", 0) > 0 and counts.get("invalid", 0) > 0, counts
    assert counts.get("error", 0) == 0, counts
