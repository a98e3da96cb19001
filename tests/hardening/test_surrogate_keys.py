"""F1: a JSON key that is a lone surrogate escape (`{"\\ud800": 1}`) gets a 4xx naming it escaped.

On main every such request got a 500 and a ~50-line traceback: the unknown-key error carried the
raw key, and rendering it as UTF-8 raised UnicodeEncodeError.
"""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient

from repnet.runtime.batchers import LiftBatcher
from repnet.server.app import build_app
from repnet.server.config import Settings
from repnet.server.metrics import Metrics
from tests.conftest import POSE_2D

POSE = '{"keypoints": ' + str(POSE_2D.tolist()) + "}"
BODIES = {
    "top level": '{"\\ud800": 1}',
    "beside poses": '{"poses": [' + POSE + '], "\\udfff\\ud800": 1}',
    "in a pose": '{"poses": [{"keypoints": ' + str(POSE_2D.tolist()) + ', "\\ud800": 1}]}',
    "in intrinsics": '{"poses": [' + POSE + '], "intrinsics": {"focal_px": [1, 1], "principal_point_px": '
    '[0, 0], "x\\ud800": 1}}',
    "as the format": '{"poses": [' + POSE + '], "format": "\\ud800"}',
    "as a coordinate": '{"poses": [{"keypoints": [["\\ud800", 1]]}]}',
}


@pytest.fixture
def app_client(engine: LiftBatcher, metrics: Metrics, settings: Settings) -> TestClient:
    return TestClient(
        build_app(engine, metrics, settings), raise_server_exceptions=False, base_url="http://localhost"
    )


@pytest.mark.parametrize("where", list(BODIES))
def test_a_lone_surrogate_is_answered_4xx_with_the_text_escaped(app_client: TestClient, where: str) -> None:
    response = app_client.post(
        "/lift", content=BODIES[where].encode(), headers={"content-type": "application/json"}
    )
    assert 400 <= response.status_code < 500, (response.status_code, response.text[:300])
    response.content.decode("utf-8")  # valid UTF-8 throughout
    if "\\ud800" in BODIES[where].split('"keypoints"')[-1] and where != "as a coordinate":
        assert "\\ud800" in response.json()["detail"][0]["message"], response.text[:300]
