"""F5: gRPC `Lift` with bytes that are not a LiftRequest gets INVALID_ARGUMENT with a plain message.

On main grpcio's own deserializer wrapper answered `UNKNOWN: Unexpected <class
'google.protobuf.message.DecodeError'>` before any service code ran.
"""

from __future__ import annotations

import grpc
import pytest

from repnet.server.metrics import Metrics
from tests.conftest import GrpcHandle

LIFT = "/repnet.v1.PoseLifter/Lift"
# A field 1 (poses) of length 100 with 2 bytes behind it; an invalid tag; an unterminated varint.
UNDECODABLE = [b"\x0a\x64\x01\x02", b"\xff\xff\xff\xff\xff", b"\x08\x80\x80\x80"]


@pytest.mark.parametrize("data", UNDECODABLE)
def test_lift_with_undecodable_bytes_is_invalid_argument_without_class_names(
    grpc_handle: GrpcHandle, metrics: Metrics, data: bytes
) -> None:
    call = grpc_handle.channel.unary_unary(LIFT)  # no serializer: the bytes go out as they are
    with pytest.raises(grpc.RpcError) as refused:
        call(data, timeout=30)
    assert refused.value.code() == grpc.StatusCode.INVALID_ARGUMENT, refused.value
    message = refused.value.details() or ""
    assert "LiftRequest" in message and "<class" not in message and "Error" not in message, message
    counted = metrics.registry.get_sample_value(
        "repnet_requests_total", {"transport": "grpc", "method": "Lift", "outcome": "invalid"}
    )
    assert counted and counted >= 1
