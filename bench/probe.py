"""The reliability probe of issues 11 and 23: 16 attacks on a fresh `repnet serve`, each held or not.

    python -m bench.probe [--json runs/probe.json] [-- extra service flags]

Ten checks of the earlier rounds (malformed and extreme input, amplification, echo, body limit,
pipelining, request smuggling, oversized and undecodable gRPC messages, idle streams) and the six of
issue 23 (F1-F6). The service runs with its defaults (one onnxruntime thread), so the slow-client
checks wait for the default timers (10 s). Prints one line per check and `N/16 held`; exits 1 if
any failed.
"""

from __future__ import annotations

import argparse
import json
import socket
import sys
import time
from collections.abc import Callable
from pathlib import Path

import grpc
import httpx
from grpc_health.v1 import health_pb2, health_pb2_grpc

if __package__ in (None, ""):  # `python bench/probe.py`
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench.server import ServiceProcess, open_fds, rss_bytes
from bench.stats import sample_poses, write_json
from repnet._proto.repnet.v1 import lifter_pb2, lifter_pb2_grpc

POSE = sample_poses(1)[0].round(1).tolist()  # (17, 2) px
Check = Callable[[ServiceProcess], str]  # returns what it saw; raises AssertionError when it failed


def _post(service: ServiceProcess, body: bytes, timeout: float = 30) -> httpx.Response:
    headers = {"content-type": "application/json"}
    return httpx.post(service.url + "/lift", content=body, headers=headers, timeout=timeout)


def _raw(service: ServiceProcess, data: bytes, timeout: float = 30) -> bytes:
    """Send `data` on a fresh connection and read until the server closes it (or `timeout`)."""
    answer = b""
    with socket.create_connection(("127.0.0.1", service.http_port), timeout=timeout) as sock:
        sock.sendall(data)
        try:
            while chunk := sock.recv(65536):
                answer += chunk
        except (TimeoutError, ConnectionResetError):
            pass
    return answer


def _stub(channel: grpc.Channel) -> lifter_pb2_grpc.PoseLifterStub:
    return lifter_pb2_grpc.PoseLifterStub(channel)  # type: ignore[no-untyped-call]


def _serving(service: ServiceProcess, timeout: float = 1.0) -> bool:
    with grpc.insecure_channel(service.target) as channel:
        reply = health_pb2_grpc.HealthStub(channel).Check(health_pb2.HealthCheckRequest(), timeout=timeout)
    return bool(reply.status == health_pb2.HealthCheckResponse.SERVING)


def nested_json(service: ServiceProcess) -> str:
    """A body nested 100,000 levels deep: 400 that says so."""
    response = _post(service, b'{"poses": ' + b"[" * 100_000 + b"]" * 100_000 + b"}")
    assert response.status_code == 400 and "nested too deeply" in response.text, response.text[:200]
    return "100,000 levels: 400, nested too deeply"


def extreme_numbers(service: ServiceProcess) -> str:
    """±1e308, NaN, ±Infinity and 1e999 as a coordinate: 4xx, never 5xx."""
    seen = []
    for value in ("1e308", "-1e308", "NaN", "Infinity", "-Infinity", "1e999"):
        body = json.dumps({"poses": [{"keypoints": POSE}]}).replace(str(POSE[0][0]), value, 1)
        seen.append(_post(service, body.encode()).status_code)
    assert all(400 <= s < 500 for s in seen), seen
    return f"±1e308, NaN, ±Infinity, 1e999: {seen}"


def error_amplification(service: ServiceProcess) -> str:
    """300,000 numbers as keypoints: one small 422, fast."""
    start = time.perf_counter()
    response = _post(service, json.dumps({"poses": [{"keypoints": [1] * 300_000}]}).encode())
    seconds = time.perf_counter() - start
    assert response.status_code == 422 and len(response.content) < 4096 and seconds < 5, (seconds, response)
    return f"300,000 numbers: 422, {len(response.content)} bytes in {seconds:.2f} s"


def echo_bound(service: ServiceProcess) -> str:
    """A 1 MB unknown key: a small 422."""
    response = _post(service, json.dumps({"poses": [{"keypoints": POSE, "k" * 1_000_000: 1}]}).encode())
    assert response.status_code == 422 and len(response.content) < 4096, len(response.content)
    return f"1 MB unknown key: 422, {len(response.content)} bytes"


def body_limit(service: ServiceProcess) -> str:
    """A 6 MiB body written whole before reading: its 413 arrives."""
    body = b"[" + b"0," * (3 * 1024 * 1024) + b"0]"
    head = b"POST /lift HTTP/1.1\r\nhost: 127.0.0.1\r\ncontent-length: %d\r\n\r\n" % len(body)
    answer = _raw(service, head + body)
    assert answer.startswith(b"HTTP/1.1 413 "), answer[:100]
    return "6 MiB body written whole before reading: 413"


def pipelining(service: ServiceProcess) -> str:
    """Three requests in one write: three answers, in order."""
    one = b"GET /healthz HTTP/1.1\r\nhost: 127.0.0.1\r\n\r\n"
    answer = _raw(
        service, one + one + b"GET /readyz HTTP/1.1\r\nhost: 127.0.0.1\r\nconnection: close\r\n\r\n"
    )
    assert answer.count(b"HTTP/1.1 200 ") == 3 and answer.rfind(b'"ready"') > answer.rfind(b'"ok"'), answer
    return "3 requests in one write: 3 answers in order"


def request_smuggling(service: ServiceProcess) -> str:
    """Content-Length and Transfer-Encoding together: 400, and nothing behind it runs."""
    data = (
        b"POST /lift HTTP/1.1\r\nhost: 127.0.0.1\r\ncontent-length: 5\r\ntransfer-encoding: chunked\r\n\r\n"
        b"0\r\n\r\nGET /metrics HTTP/1.1\r\nhost: 127.0.0.1\r\n\r\n"
    )
    answer = _raw(service, data)
    assert answer.startswith(b"HTTP/1.1 400 ") and answer.count(b"HTTP/1.1") == 1, answer[:200]
    return "Content-Length with Transfer-Encoding: one 400, the smuggled request never runs"


def grpc_oversized(service: ServiceProcess) -> str:
    """A 6 MB Lift: RESOURCE_EXHAUSTED, health still SERVING."""
    pose = lifter_pb2.Pose2D(keypoints=[1.0] * 34)
    request = lifter_pb2.LiftRequest(poses=[pose] * 40_000)  # ~6 MB > the 4 MiB limit
    with grpc.insecure_channel(service.target) as channel:
        try:
            _stub(channel).Lift(request, timeout=30)
            raise AssertionError("a 6 MB message was accepted")
        except grpc.RpcError as err:
            code = err.code()
    assert code == grpc.StatusCode.RESOURCE_EXHAUSTED and _serving(service), code
    return f"6 MB Lift: {code.name}, health SERVING"


def idle_streams(service: ServiceProcess) -> str:
    """70 streams that went quiet: health and Lift still answer within 1 s."""
    frame = lifter_pb2.LiftFrame(frame_id=0, pose=lifter_pb2.Pose2D(keypoints=sum(POSE, [])))
    with grpc.insecure_channel(service.target) as channel:
        stub = _stub(channel)
        calls = []
        for _ in range(70):  # more than REPNET_GRPC_MAX_STREAMS (64)

            def one() -> object:
                yield frame
                time.sleep(30)  # then quiet, never half-closing

            calls.append(stub.LiftStream(one(), timeout=20))
        time.sleep(1.0)
        start = time.perf_counter()
        serving = _serving(service)
        reply = stub.Lift(lifter_pb2.LiftRequest(poses=[frame.pose]), timeout=5)
        seconds = time.perf_counter() - start
        for call in calls:
            call.cancel()
    assert serving and len(reply.poses) == 1 and seconds < 1, seconds
    return f"70 quiet streams: health SERVING and Lift answered in {seconds * 1e3:.0f} ms"


def undecodable_frame(service: ServiceProcess) -> str:
    """An undecodable LiftStream frame: INVALID_ARGUMENT, no class name."""
    with grpc.insecure_channel(service.target) as channel:
        call = channel.stream_stream("/repnet.v1.PoseLifter/LiftStream")
        try:
            list(call(iter([b"\xff\xff\xff\xff\x0f"]), timeout=10))
            raise AssertionError("an undecodable frame was answered")
        except grpc.RpcError as err:
            code, message = err.code(), err.details() or ""
    assert code == grpc.StatusCode.INVALID_ARGUMENT and "<class" not in message, (code, message)
    return f"LiftStream frame ff ff ff ff 0f: {code.name}"


def f1_surrogate_key(service: ServiceProcess) -> str:
    """F1: {"\\ud800": 1} at the top level and in a pose: 4xx."""
    statuses = [_post(service, b).status_code for b in (b'{"\\ud800": 1}', b'{"poses": [{"\\ud800": 1}]}')]
    assert all(400 <= s < 500 for s in statuses), statuses
    return f'{{"\\ud800": 1}} top level and in a pose: {statuses}'


def f2_slow_bodies(service: ServiceProcess) -> str:
    """F2: 130 one-byte bodies: a normal /lift gets 200, each of them 408."""
    head = b"POST /lift HTTP/1.1\r\nhost: 127.0.0.1\r\ncontent-length: 1000\r\n\r\n{"
    socks = [socket.create_connection(("127.0.0.1", service.http_port), timeout=60) for _ in range(130)]
    try:
        for sock in socks:
            sock.sendall(head)
        time.sleep(0.5)
        status = _post(service, json.dumps({"poses": [{"keypoints": POSE}]}).encode()).status_code
        answers = [sock.recv(64) for sock in socks]  # the 408, once the body deadline passes
    finally:
        for sock in socks:
            sock.close()
    held = sum(a.startswith(b"HTTP/1.1 408 ") for a in answers)
    assert status == 200 and held == len(socks), (status, held)
    return f"130 one-byte bodies: a normal /lift {status}, all 130 got 408"


def f3_header_lines(service: ServiceProcess) -> str:
    """F3: 4 header lines of 32 MiB: 431 each, no memory kept."""
    before = rss_bytes(service.pid)
    answers = []
    for _ in range(4):
        with socket.create_connection(("127.0.0.1", service.http_port), timeout=30) as sock:
            sock.sendall(b"GET /readyz HTTP/1.1\r\nx-long: ")
            try:
                for _ in range(512):  # 32 MiB
                    sock.sendall(b"a" * 65536)
            except OSError:
                pass
            answers.append(sock.recv(64))
    grown = (rss_bytes(service.pid) - before) / 2**20
    assert all(a.startswith(b"HTTP/1.1 431 ") for a in answers) and grown < 32, (answers, grown)
    return f"4 x 32 MiB header lines: 431 each, RSS {grown:+.1f} MB"


def f4_idle_connections(service: ServiceProcess) -> str:
    """F4: 1,200 idle connections: probes answer within 1 s, the header timer closes them."""
    socks = [socket.create_connection(("127.0.0.1", service.http_port), timeout=30) for _ in range(1200)]
    try:
        for sock in socks[1000:]:
            sock.sendall(b"GET /readyz HTTP/1.1\r\nhost: 127.0.0.1\r\nx-half: ab")
        start = time.perf_counter()
        ready = httpx.get(service.url + "/readyz", timeout=1).status_code
        serving = _serving(service)
        seconds = time.perf_counter() - start
        fds = open_fds(service.pid)
        closed = sum(not sock.recv(64).startswith(b"HTTP/1.1 2") for sock in socks)  # after the timer
    finally:
        for sock in socks:
            sock.close()
    assert ready == 200 and serving and seconds < 1 and closed == len(socks), (ready, serving, seconds)
    return f"1200 idle: /readyz and health in {seconds * 1e3:.0f} ms, {fds} fds, all closed by the timer"


def f5_undecodable_lift(service: ServiceProcess) -> str:
    """F5: undecodable Lift bytes: INVALID_ARGUMENT with a plain message."""
    with grpc.insecure_channel(service.target) as channel:
        try:
            channel.unary_unary("/repnet.v1.PoseLifter/Lift")(b"\xff\xff\xff\xff\x0f", timeout=10)
            raise AssertionError("undecodable bytes were answered")
        except grpc.RpcError as err:
            code, message = err.code(), err.details() or ""
    assert code == grpc.StatusCode.INVALID_ARGUMENT and "<class" not in message, (code, message)
    return f"Lift ff ff ff ff 0f: {code.name}: {message}"


def expire_lifts(target: str, request: lifter_pb2.LiftRequest, calls: int, deadline_s: float) -> list[str]:
    """`calls` concurrent Lifts of `request` with a deadline each; the status name each ended with."""
    codes = []
    with grpc.insecure_channel(target) as channel:
        futures = [_stub(channel).Lift.future(request, timeout=deadline_s) for _ in range(calls)]
        for future in futures:
            try:
                future.result()
                codes.append("OK")
            except grpc.RpcError as err:
                codes.append(err.code().name)
    return codes


def f6_expired_lifts(service: ServiceProcess) -> str:
    """F6: 40 x Lift(1024) with a 20 ms deadline: no RESOURCE_EXHAUSTED, counted as cancelled."""
    request = lifter_pb2.LiftRequest(poses=[lifter_pb2.Pose2D(keypoints=sum(POSE, []))] * 1024)
    codes = expire_lifts(service.target, request, 40, 0.02)
    time.sleep(2)
    metrics = httpx.get(service.url + "/metrics", timeout=10).text
    lines = [line for line in metrics.splitlines() if line.startswith('repnet_requests_total{method="Lift"')]
    outcomes = {line.split('outcome="')[1].split('"')[0]: float(line.split()[-1]) for line in lines}
    assert "RESOURCE_EXHAUSTED" not in codes and outcomes.get("error", 0) == 0, (codes, outcomes)
    assert outcomes.get("cancelled", 0) >= 1, outcomes
    return f"40 x Lift(1024) at 20 ms: no RESOURCE_EXHAUSTED, outcomes {outcomes}"


CHECKS: list[tuple[str, Check]] = [
    ("nested JSON", nested_json),
    ("±1e308, NaN, Infinity", extreme_numbers),
    ("error amplification", error_amplification),
    ("echo bound", echo_bound),
    ("body limit, whole body before reading", body_limit),
    ("pipelining", pipelining),
    ("request smuggling", request_smuggling),
    ("oversized gRPC message", grpc_oversized),
    ("idle streams vs health", idle_streams),
    ("undecodable stream frame", undecodable_frame),
    ("F1 lone surrogate key", f1_surrogate_key),
    ("F2 slow bodies", f2_slow_bodies),
    ("F3 endless header lines", f3_header_lines),
    ("F4 idle connections", f4_idle_connections),
    ("F5 undecodable Lift", f5_undecodable_lift),
    ("F6 expired Lifts", f6_expired_lifts),
]


def main(argv: list[str] | None = None) -> int:
    """Run every check against one fresh service; print each and the count that held."""
    parser = argparse.ArgumentParser(prog="python -m bench.probe", description=__doc__.split("\n")[0])
    parser.add_argument("--json", type=Path, help="also write the results here")
    parser.add_argument("flags", nargs="*", help="flags for python -m repnet serve (after --)")
    args = parser.parse_args(argv)
    results = []
    with ServiceProcess("--intra-op-threads", "1", *args.flags) as service:
        for name, check in CHECKS:
            try:
                seen, held = check(service), True
            except (AssertionError, OSError, grpc.RpcError, httpx.HTTPError) as err:
                seen, held = f"{type(err).__name__}: {err}"[:300], False
            results.append({"check": name, "held": held, "seen": seen})
            print(f"{'held' if held else 'FAILED':6}  {name}: {seen}", flush=True)
    held = sum(r["held"] for r in results)
    print(f"{held}/{len(results)} held")
    if args.json:
        write_json(args.json, {"flags": args.flags, "results": results})
    return 0 if held == len(results) else 1


if __name__ == "__main__":
    raise SystemExit(main())
