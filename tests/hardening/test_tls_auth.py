"""TLS (and mutual TLS) on both servers, and API keys on /lift, /v1/* and both gRPC methods.

On main both servers spoke plaintext only and anyone who reached a port could lift. The
certificates here are made by the test: a CA, the server's (for 127.0.0.1) and a client's.
"""

from __future__ import annotations

import datetime
import hmac
import ipaddress
import logging
import ssl
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import grpc
import httpx
import numpy as np
import pytest
from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID
from grpc_health.v1 import health_pb2, health_pb2_grpc

from repnet._proto.repnet.v1 import lifter_pb2, lifter_pb2_grpc
from repnet.client.http import LiftClient, LiftClientError
from repnet.client.stream import StreamClient
from repnet.runtime.lifter import Lifter
from repnet.server import auth
from repnet.server.app import Service, main
from repnet.server.auth import UNAUTHENTICATED_MESSAGE
from repnet.server.config import Settings
from tests.conftest import POSE_2D
from tests.hardening.conftest import running

KEYS = ("k-first-0123456789abcdef", "k-second-fedcba9876543210")
BODY = {"poses": [{"keypoints": POSE_2D.tolist()}]}


@dataclass(frozen=True)
class Pki:
    ca: Path
    server_cert: Path
    server_key: Path
    client_cert: Path
    client_key: Path


def _issue(name: str, key: ec.EllipticCurvePrivateKey, issuer: x509.Name, signer: ec.EllipticCurvePrivateKey,
           *, ca: bool = False, server: bool = False) -> x509.Certificate:  # fmt: skip
    now = datetime.datetime.now(datetime.timezone.utc)
    builder = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)]))
        .issuer_name(issuer)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=1))
        .add_extension(x509.BasicConstraints(ca=ca, path_length=None), critical=True)
    )
    if server:
        names = [x509.DNSName("localhost"), x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]
        builder = builder.add_extension(x509.SubjectAlternativeName(names), critical=False)
        builder = builder.add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH]), False)
    elif not ca:
        builder = builder.add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.CLIENT_AUTH]), False)
    return builder.sign(signer, hashes.SHA256())


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Pki:
    folder = tmp_path_factory.mktemp("pki")
    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "repnet test CA")])
    ca = _issue("repnet test CA", ca_key, ca_name, ca_key, ca=True)
    files = {"ca": ca.public_bytes(serialization.Encoding.PEM)}
    for who in ("server", "client"):
        key = ec.generate_private_key(ec.SECP256R1())
        cert = _issue(f"repnet test {who}", key, ca_name, ca_key, server=who == "server")
        files[f"{who}_cert"] = cert.public_bytes(serialization.Encoding.PEM)
        files[f"{who}_key"] = key.private_bytes(
            serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
        )
    for name, data in files.items():
        (folder / f"{name}.pem").write_bytes(data)
    names = ("ca", "server_cert", "server_key", "client_cert", "client_key")
    return Pki(*(folder / f"{name}.pem" for name in names))


def _settings(**extra: object) -> Settings:
    return Settings(host="127.0.0.1", http_port=0, grpc_port=0, intra_op_threads=1, shutdown_grace_s=1,
                    **extra)  # type: ignore[arg-type]  # fmt: skip


def _ports(service: Service) -> tuple[int, int]:
    return service.http.servers[0].sockets[0].getsockname()[1], service.grpc_server.port


@pytest.fixture(scope="module")
def tls_service(lifter: Lifter, pki: Pki) -> Iterator[tuple[int, int]]:
    with running(_settings(tls_cert=pki.server_cert, tls_key=pki.server_key), lifter) as service:
        yield _ports(service)


def test_both_servers_speak_tls_with_the_certificate_made_here(
    tls_service: tuple[int, int], pki: Pki
) -> None:
    http_port, grpc_port = tls_service
    with LiftClient(f"https://127.0.0.1:{http_port}", ca_file=pki.ca, retries=0) as client:
        assert client.lift(POSE_2D).pose_3d.shape == (17, 3)
    with pytest.raises(httpx.HTTPError):  # plaintext to the TLS port
        httpx.get(f"http://127.0.0.1:{http_port}/readyz", timeout=5)
    with pytest.raises(httpx.HTTPError):  # a certificate no trusted CA signed
        httpx.get(f"https://127.0.0.1:{http_port}/readyz", timeout=5)
    with StreamClient(f"127.0.0.1:{grpc_port}", ca_file=pki.ca, timeout=30) as client:
        assert len(client.lift_batch(np.stack([POSE_2D] * 3))) == 3
        assert [r.error for r in client.stream(np.stack([POSE_2D] * 2))] == [None, None]
    with grpc.insecure_channel(f"127.0.0.1:{grpc_port}") as plain:
        with pytest.raises(grpc.RpcError):
            health_pb2_grpc.HealthStub(plain).Check(health_pb2.HealthCheckRequest(), timeout=5)


def test_mutual_tls_refuses_a_client_without_a_certificate(lifter: Lifter, pki: Pki) -> None:
    settings = _settings(tls_cert=pki.server_cert, tls_key=pki.server_key, tls_client_ca=pki.ca)
    with running(settings, lifter) as service:
        http_port, grpc_port = _ports(service)
        url = f"https://127.0.0.1:{http_port}/readyz"
        anonymous = ssl.create_default_context(cafile=str(pki.ca))
        with pytest.raises(httpx.HTTPError):
            httpx.get(url, verify=anonymous, timeout=5).raise_for_status()
        known = ssl.create_default_context(cafile=str(pki.ca))
        known.load_cert_chain(pki.client_cert, pki.client_key)
        assert httpx.get(url, verify=known, timeout=5).status_code == 200

        def health(credentials: grpc.ChannelCredentials) -> int:
            with grpc.secure_channel(f"127.0.0.1:{grpc_port}", credentials) as channel:
                stub = health_pb2_grpc.HealthStub(channel)
                return stub.Check(health_pb2.HealthCheckRequest(), timeout=5).status

        with pytest.raises(grpc.RpcError):
            health(grpc.ssl_channel_credentials(pki.ca.read_bytes()))
        mutual = grpc.ssl_channel_credentials(
            pki.ca.read_bytes(), pki.client_key.read_bytes(), pki.client_cert.read_bytes()
        )
        assert health(mutual) == health_pb2.HealthCheckResponse.SERVING


@pytest.fixture(scope="module")
def keyed_service(lifter: Lifter, tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[int, int]]:
    keys = tmp_path_factory.mktemp("keys") / "api-keys"
    keys.write_text("# the service's API keys\n\n" + "\n".join(f"  {k}  " for k in KEYS) + "\n")
    with running(_settings(api_keys_file=keys, log_level="debug"), lifter) as service:
        yield _ports(service)


def test_http_needs_a_key_on_lift_and_v1_and_answers_401_alike(keyed_service: tuple[int, int]) -> None:
    url = f"http://127.0.0.1:{keyed_service[0]}"
    wrong = [{}, {"authorization": "Bearer nope"}, {"authorization": f"Basic {KEYS[0]}"},
             {"authorization": f"Bearer {KEYS[0]}x"}, {"authorization": "Bearer"}]  # fmt: skip
    answers = []
    for headers in wrong:
        for method, path in (("POST", "/lift"), ("GET", "/v1/model")):
            response = httpx.request(method, url + path, json=BODY, headers=headers, timeout=30)
            assert response.status_code == 401 and response.headers["www-authenticate"] == "Bearer"
            answers.append(response.content)
    assert set(answers) == {b'{"detail": "missing or invalid API key"}'}  # nothing about what was wrong
    for key in KEYS:
        with LiftClient(url, api_key=key, retries=0) as client:
            assert client.lift(POSE_2D).pose_3d.shape == (17, 3)
        assert httpx.get(url + "/v1/model", headers={"authorization": f"bearer {key}"}).status_code == 200
    for path in ("/healthz", "/readyz", "/metrics", "/docs", "/openapi.json"):  # open, as documented
        assert httpx.get(url + path, timeout=30).status_code == 200, path
    with LiftClient(url, retries=0) as client, pytest.raises(LiftClientError) as refused:
        client.lift(POSE_2D)
    assert refused.value.status == 401
    metrics = httpx.get(url + "/metrics").text
    assert 'outcome="unauthenticated"' in metrics and not any(k in metrics for k in KEYS)


def test_grpc_needs_a_key_on_both_methods_and_answers_unauthenticated_alike(
    keyed_service: tuple[int, int],
) -> None:
    target = f"127.0.0.1:{keyed_service[1]}"
    request = lifter_pb2.LiftRequest(poses=[lifter_pb2.Pose2D(keypoints=POSE_2D.ravel().tolist())])
    frame = lifter_pb2.LiftFrame(frame_id=1, pose=request.poses[0])
    with grpc.insecure_channel(target) as channel:
        stub = lifter_pb2_grpc.PoseLifterStub(channel)  # type: ignore[no-untyped-call]
        for metadata in ((), (("authorization", "Bearer nope"),), (("authorization", KEYS[0]),)):
            with pytest.raises(grpc.RpcError) as unary:
                stub.Lift(request, metadata=metadata, timeout=30)
            with pytest.raises(grpc.RpcError) as stream:
                list(stub.LiftStream(iter([frame]), metadata=metadata, timeout=30))
            for refused in (unary.value, stream.value):
                assert refused.code() == grpc.StatusCode.UNAUTHENTICATED
                assert refused.details() == UNAUTHENTICATED_MESSAGE
        health = health_pb2_grpc.HealthStub(channel).Check(health_pb2.HealthCheckRequest(), timeout=30)
        assert health.status == health_pb2.HealthCheckResponse.SERVING  # open, as documented
    with StreamClient(target, api_key=KEYS[1], timeout=30) as client:
        assert len(client.lift_batch(np.stack([POSE_2D] * 2))) == 2
        assert [r.error for r in client.stream(np.stack([POSE_2D] * 2))] == [None, None]


def test_keys_are_compared_in_constant_time_and_never_logged(
    keyed_service: tuple[int, int], monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    calls = []
    compare = hmac.compare_digest

    def counting(a: bytes, b: bytes) -> bool:
        calls.append((len(a), len(b)))
        return compare(a, b)

    monkeypatch.setattr(auth.hmac, "compare_digest", counting)
    url = f"http://127.0.0.1:{keyed_service[0]}"
    with caplog.at_level(logging.DEBUG):
        for key in (KEYS[0], "x", "y" * 500):
            httpx.post(url + "/lift", json=BODY, headers={"authorization": f"Bearer {key}"}, timeout=30)
        with StreamClient(f"127.0.0.1:{keyed_service[1]}", api_key=KEYS[1], timeout=30) as client:
            client.lift_batch(POSE_2D[None])
    # every key compared on every try, whether the first matched or not, on digests of one length
    assert len(calls) == 4 * len(KEYS) and set(calls) == {(32, 32)}
    assert caplog.records and not any(k in record.getMessage() for record in caplog.records for k in KEYS)


def test_a_key_that_is_not_the_certificates_says_so_at_start(
    pki: Pki, caplog: pytest.LogCaptureFixture
) -> None:
    """Issue 30: the start failed with "cannot bind the gRPC server ... Failed to bind"."""
    flags = ["--tls-cert", str(pki.server_cert), "--tls-key", str(pki.client_key)]
    assert main([*flags, "--http-port", "0", "--grpc-port", "0", "--workers", "1"]) == 1
    (line,) = [r.getMessage() for r in caplog.records if "cannot start" in r.getMessage()]
    assert "the key does not match the certificate" in line and "bind" not in line, line
    not_pem = pki.server_key.with_name("garbage.pem")
    not_pem.write_text("not a key")
    caplog.clear()
    assert main(["--tls-cert", str(pki.server_cert), "--tls-key", str(not_pem), "--http-port", "0",
                 "--grpc-port", "0", "--workers", "1"]) == 1  # fmt: skip
    (line,) = [r.getMessage() for r in caplog.records if "cannot start" in r.getMessage()]
    assert "garbage.pem" in line and "cannot be used together" in line, line


def test_settings_refuse_half_a_tls_configuration(pki: Pki) -> None:
    with pytest.raises(ValueError, match="tls_cert and tls_key"):
        Settings(tls_cert=pki.server_cert)
    with pytest.raises(ValueError, match="needs tls_cert"):
        Settings(tls_client_ca=pki.ca)
