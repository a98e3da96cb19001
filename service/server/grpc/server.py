"""The gRPC server: grpc.aio on its own event loop thread, with health and reflection; create_server."""

from __future__ import annotations

import asyncio
import logging
import ssl
import threading
from collections.abc import Awaitable, Callable, Coroutine
from concurrent import futures
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeAlias

import grpc
from google.protobuf.message import DecodeError
from grpc_health.v1 import health, health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection

from repnet._proto.repnet.v1 import lifter_pb2
from repnet.core.errors import Violation
from repnet.core.inputs import Limits
from repnet.runtime.batchers import LiftBatcher
from repnet.runtime.catalog import Catalog
from repnet.runtime.plans import TemporalModels
from repnet.server.auth import UNAUTHENTICATED_MESSAGE, ApiKeys
from repnet.server.grpc.api import SERVICE_NAME, TRANSPORT, PoseLifterServicer
from repnet.server.metrics import INVALID, UNAUTHENTICATED, Metrics

log = logging.getLogger(__name__)
Handler: TypeAlias = "grpc.RpcMethodHandler[Any, Any]"  # generic in the stubs only


def _log_failure(done: futures.Future[None]) -> None:
    if not done.cancelled() and (err := done.exception()) is not None:
        log.error("updating the gRPC health status failed: %s", err)


class Health:
    """The standard gRPC health service, set from any thread: SERVING or NOT_SERVING for the whole
    server ("") and for repnet.v1.PoseLifter."""

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self.loop = loop
        self.servicer = health.aio.HealthServicer()
        self.serving = False  # what was reported last

    def _call(self, coroutine: Coroutine[Any, Any, None]) -> None:
        """Schedule `coroutine` on the server's loop without waiting for it: the caller may be a signal
        handler, which must not block on another thread (that thread may wait for a lock the
        interrupted code holds). Calls scheduled later, such as the server's stop, run after it."""
        try:
            done = asyncio.run_coroutine_threadsafe(coroutine, self.loop)
        except RuntimeError:  # the loop has closed: the server has stopped, there is nobody to tell
            coroutine.close()
            return
        done.add_done_callback(_log_failure)

    async def set_status(self, serving: bool) -> None:
        """Report SERVING or NOT_SERVING (on the server's loop)."""
        status = (
            health_pb2.HealthCheckResponse.SERVING if serving else health_pb2.HealthCheckResponse.NOT_SERVING
        )
        for name in ("", SERVICE_NAME):
            await self.servicer.set(name, status)
        self.serving = serving

    def set(self, serving: bool) -> None:
        """Report SERVING or NOT_SERVING (from any thread)."""
        self._call(self.set_status(serving))

    def enter_graceful_shutdown(self) -> None:
        """NOT_SERVING from now on, whatever is set later (what SIGTERM does first)."""
        self._call(self.servicer.enter_graceful_shutdown())
        self.serving = False


class GrpcServer:
    """A grpc.aio server on its own event loop thread, driven from synchronous code.

    Built by create_server (bound, not started); start() serves; stop(grace) stops accepting calls,
    gives the calls in progress `grace` seconds and returns an Event set once it has stopped.
    """

    def __init__(self, build: Callable[[Health], Coroutine[Any, Any, tuple[grpc.aio.Server, int]]]) -> None:
        self.loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self.loop.run_forever, name="repnet-grpc", daemon=True)
        self._thread.start()
        self.health = Health(self.loop)
        self._stopped: threading.Event | None = None
        try:
            self.server, self.port = asyncio.run_coroutine_threadsafe(build(self.health), self.loop).result()
        except BaseException:
            self._close_loop()
            raise

    def start(self) -> None:
        """Serve (the server was bound when built)."""
        asyncio.run_coroutine_threadsafe(self.server.start(), self.loop).result()

    def stop(self, grace: float | None) -> threading.Event:
        """Stop accepting calls, give those in progress `grace` seconds; the Event is set once stopped."""
        if self._stopped is None:
            self._stopped = threading.Event()
            stopping = asyncio.run_coroutine_threadsafe(self.server.stop(grace), self.loop)
            threading.Thread(
                target=self._finish, args=(stopping,), name="repnet-grpc-stop", daemon=True
            ).start()
        return self._stopped

    def _finish(self, stopping: futures.Future[None]) -> None:
        try:
            stopping.result()
        except Exception:
            log.exception("the gRPC server did not stop cleanly")
        finally:
            self._close_loop()
            if self._stopped is not None:
                self._stopped.set()

    def _close_loop(self) -> None:
        """Stop the event loop thread and close the loop (from any thread but the loop's own)."""
        if not self.loop.is_closed():
            self.loop.call_soon_threadsafe(self.loop.stop)
            self._thread.join(timeout=10)
            if not self.loop.is_running():
                self.loop.close()


@dataclass(frozen=True)
class GrpcTls:
    """What the gRPC server serves TLS with: PEM bytes; client_ca set: mutual TLS."""

    cert_chain: bytes
    private_key: bytes
    client_ca: bytes | None = None

    def credentials(self) -> grpc.ServerCredentials:
        """The server credentials (requiring a client certificate signed by client_ca, if set)."""
        return grpc.ssl_server_credentials(
            [(self.private_key, self.cert_chain)],
            root_certificates=self.client_ca,
            require_client_auth=self.client_ca is not None,
        )


def read_tls(cert: Path | None, key: Path | None, client_ca: Path | None) -> GrpcTls | None:
    """The TLS of PEM files as read now (None without a certificate: plaintext); OSError if one
    cannot be read, or saying so when the key is not the certificate's (checked here with Python's
    ssl, the check HTTPS makes: grpc would only say that it failed to bind)."""
    if cert is None or key is None:
        return None
    try:
        ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER).load_cert_chain(cert, key)
    except ssl.SSLError as err:
        why = "the key does not match the certificate" if "MISMATCH" in str(err).upper() else "not PEM"
        raise OSError(
            f"TLS: REPNET_TLS_CERT {cert} and REPNET_TLS_KEY {key} cannot be used together: {why} "
            f"({err.reason})"
        ) from None
    return GrpcTls(cert.read_bytes(), key.read_bytes(), None if client_ca is None else client_ca.read_bytes())


async def _deny_unary(request: object, context: grpc.aio.ServicerContext[Any, Any]) -> None:
    await context.abort(grpc.StatusCode.UNAUTHENTICATED, UNAUTHENTICATED_MESSAGE)


async def _deny_stream(requests: object, context: grpc.aio.ServicerContext[Any, Any]) -> None:
    await context.abort(grpc.StatusCode.UNAUTHENTICATED, UNAUTHENTICATED_MESSAGE)


class ApiKeyInterceptor(grpc.aio.ServerInterceptor):
    """repnet.v1.PoseLifter's methods need `authorization: Bearer KEY` metadata with a key of `keys`;
    otherwise UNAUTHENTICATED with one message whatever was wrong. Health and reflection stay open."""

    def __init__(self, keys: ApiKeys, metrics: Metrics) -> None:
        self.keys = keys
        self.metrics = metrics

    async def intercept_service(
        self,
        continuation: Callable[[grpc.HandlerCallDetails], Awaitable[Handler | None]],
        handler_call_details: grpc.HandlerCallDetails,
    ) -> Handler | None:
        """The method's handler, or one that refuses the call."""
        details = handler_call_details
        handler = await continuation(details)
        service, _, method = details.method.lstrip("/").partition("/")
        if handler is None or service != SERVICE_NAME:
            return handler
        header = next((v for k, v in details.invocation_metadata or () if k == "authorization"), None)
        if self.keys.accepts_header(header if isinstance(header, str) else None):
            return handler
        self.metrics.finish(TRANSPORT, method, UNAUTHENTICATED, 0.0)
        if handler.request_streaming:
            return grpc.stream_stream_rpc_method_handler(_deny_stream)
        return grpc.unary_unary_rpc_method_handler(_deny_unary)


class UnreadableRequest:
    """What read_lift_request gives for bytes that are not a LiftRequest."""

    message = "the request cannot be decoded as a repnet.v1.LiftRequest (protobuf)"


def read_lift_request(data: bytes) -> lifter_pb2.LiftRequest | UnreadableRequest:
    """Lift's request deserializer: the message, or UnreadableRequest for the handler to answer
    INVALID_ARGUMENT (an exception here would reach the client as UNKNOWN with a class name)."""
    try:
        return lifter_pb2.LiftRequest.FromString(data)
    except DecodeError:
        return UnreadableRequest()


def add_servicer(servicer: PoseLifterServicer, server: grpc.aio.Server) -> None:
    """Register repnet.v1.PoseLifter as the generated add_PoseLifterServicer_to_server does, but
    with Lift's request read by read_lift_request: grpcio answers a message that fails to decode
    with UNKNOWN and a Python class name before any servicer code runs."""

    async def lift(
        request: lifter_pb2.LiftRequest | UnreadableRequest, context: grpc.aio.ServicerContext[Any, Any]
    ) -> lifter_pb2.LiftResponse:
        if isinstance(request, UnreadableRequest):
            servicer.metrics.reject(TRANSPORT, [Violation("request", request.message, "malformed")])
            servicer.metrics.finish(TRANSPORT, "Lift", INVALID, 0.0)
            await context.abort(grpc.StatusCode.INVALID_ARGUMENT, request.message)
        return await servicer.Lift(request, context)

    handlers: dict[str, Handler] = {
        "Lift": grpc.unary_unary_rpc_method_handler(
            lift,
            request_deserializer=read_lift_request,
            response_serializer=lifter_pb2.LiftResponse.SerializeToString,
        ),
        "LiftStream": grpc.stream_stream_rpc_method_handler(
            servicer.LiftStream,
            request_deserializer=lifter_pb2.LiftFrame.FromString,
            response_serializer=lifter_pb2.LiftFrameResult.SerializeToString,
        ),
    }
    server.add_generic_rpc_handlers((grpc.method_handlers_generic_handler(SERVICE_NAME, handlers),))
    server.add_registered_method_handlers(SERVICE_NAME, handlers)


def create_server(
    engine: LiftBatcher | Catalog,
    metrics: Metrics,
    limits: Limits,
    address: str,
    *,
    tls: GrpcTls | None,
    api_keys: ApiKeys | None,
    workers: int,
    max_streams: int,
    stream_idle_timeout_s: float,
    max_message_bytes: int,
    max_client_streams: int | None = None,
    stream_window_poses: int,
    temporal: TemporalModels | None = None,
    reuse_port: bool = False,
) -> GrpcServer:
    """A gRPC server (not started) bound to `address`, with health (`.health`) and reflection.

    At most `workers` Lift calls and `max_streams` open streams at once (`max_client_streams` of one
    client; None: max_streams); calls beyond get
    RESOURCE_EXHAUSTED. Health and reflection have no limit: a health check always answers.
    `tls`: serve over TLS (None: plaintext). `api_keys`: the PoseLifter methods need one (None: open).
    """

    async def build(status: Health) -> tuple[grpc.aio.Server, int]:
        server = grpc.aio.server(
            # so_reuseport 0: a second server on a taken port fails instead of sharing it; a worker's
            # (reuse_port) shares it with the others (the supervisor holds the port: server.workers).
            options=[
                ("grpc.max_receive_message_length", max_message_bytes),
                ("grpc.so_reuseport", 1 if reuse_port else 0),
            ],
            interceptors=[] if api_keys is None else [ApiKeyInterceptor(api_keys, metrics)],
        )
        servicer = PoseLifterServicer(
            engine,
            metrics,
            limits,
            stream_window_poses=stream_window_poses,
            max_unary=workers,
            max_streams=max_streams,
            max_client_streams=max_streams if max_client_streams is None else max_client_streams,
            stream_idle_timeout_s=stream_idle_timeout_s,
            temporal=temporal,
        )
        add_servicer(servicer, server)
        health_pb2_grpc.add_HealthServicer_to_server(status.servicer, server)
        names = (SERVICE_NAME, health.SERVICE_NAME, reflection.SERVICE_NAME)
        reflection.enable_server_reflection(names, server)
        try:
            if tls is None:
                port = server.add_insecure_port(address)
            else:
                port = server.add_secure_port(address, tls.credentials())
        except RuntimeError as err:  # grpc's way to say the port is taken
            raise OSError(f"cannot bind the gRPC server to {address}: {err}") from err
        if port == 0:
            raise OSError(f"cannot bind the gRPC server to {address}")
        await status.set_status(servicer.models.ready)
        return server, port

    return GrpcServer(build)
