"""The gRPC server: grpc.aio on its own event loop thread, with health and reflection; create_server."""

from __future__ import annotations

import asyncio
import logging
import threading
from collections.abc import Callable, Coroutine
from concurrent import futures
from typing import Any

import grpc
from grpc_health.v1 import health, health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection

from service._proto.repnet.v1 import lifter_pb2_grpc
from service.engine import Engine
from service.grpc_api import SERVICE_NAME, PoseLifterServicer
from service.keypoints import Limits
from service.metrics import Metrics
from service.tracking import TemporalModels

log = logging.getLogger(__name__)


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


def create_server(
    engine: Engine,
    metrics: Metrics,
    limits: Limits,
    address: str,
    *,
    workers: int,
    max_streams: int,
    stream_idle_timeout_s: float,
    max_message_bytes: int,
    stream_window: int,
    temporal: TemporalModels | None = None,
) -> GrpcServer:
    """A gRPC server (not started) bound to `address`, with health (`.health`) and reflection.

    At most `workers` Lift calls and `max_streams` open streams at once; calls beyond get
    RESOURCE_EXHAUSTED. Health and reflection have no limit: a health check always answers.
    """

    async def build(status: Health) -> tuple[grpc.aio.Server, int]:
        server = grpc.aio.server(
            # so_reuseport 0: a second server on a taken port fails instead of sharing it.
            options=[("grpc.max_receive_message_length", max_message_bytes), ("grpc.so_reuseport", 0)],
        )
        servicer = PoseLifterServicer(
            engine,
            metrics,
            limits,
            stream_window=stream_window,
            max_unary=workers,
            max_streams=max_streams,
            stream_idle_timeout_s=stream_idle_timeout_s,
            temporal=temporal,
        )
        lifter_pb2_grpc.add_PoseLifterServicer_to_server(servicer, server)  # type: ignore[no-untyped-call]
        health_pb2_grpc.add_HealthServicer_to_server(status.servicer, server)
        names = (SERVICE_NAME, health.SERVICE_NAME, reflection.SERVICE_NAME)
        reflection.enable_server_reflection(names, server)
        try:
            port = server.add_insecure_port(address)
        except RuntimeError as err:  # grpc's way to say the port is taken
            raise OSError(f"cannot bind the gRPC server to {address}: {err}") from err
        if port == 0:
            raise OSError(f"cannot bind the gRPC server to {address}")
        await status.set_status(engine.ready)
        return server, port

    return GrpcServer(build)
