"""The HTTP server: uvicorn with an accept path that keeps up under load and a lossless shutdown."""

from __future__ import annotations

import asyncio
import contextlib
import ctypes
import errno
import logging
import resource
import socket
import ssl
import struct
import sys
from collections.abc import Generator

import uvicorn
from fastapi import FastAPI

from repnet.server.config import Settings
from repnet.server.http.protocol import ConnectionLimits, guarded_protocol

log = logging.getLogger(__name__)

# How long shutdown waits for a connection accepted just before it to send its request.
FIRST_REQUEST_WAIT_S = 2.0
# File descriptors kept free of HTTP connections: gRPC connections, health probes, the model, logs.
RESERVED_FDS = 128
# How long the accept path rests when the process is out of file descriptors.
ACCEPT_RETRY_S = 0.1
# Most connections taken per readable event: a connection closed to make room for a new one (the
# idle longest, at the connection cap) frees its descriptor only on the loop's next turn, so a
# bigger burst could run past the descriptors RESERVED_FDS keeps free.
ACCEPT_BATCH = 64
SO_ATTACH_FILTER = 26  # Linux <asm-generic/socket.h>; the socket module does not name it


def stop_handshakes(listener: socket.socket) -> None:
    """Make a listening socket drop every packet from now on (a classic BPF program "return 0"):
    no handshake completes any more, so its backlog can be drained before it closes without a
    connection slipping in to be reset. Clients whose SYN is dropped resend it and find the port
    closed. Linux only; elsewhere nothing changes."""
    if sys.platform != "linux":
        return
    drop_all = ctypes.create_string_buffer(struct.pack("HBBI", 0x06, 0, 0, 0))  # BPF_RET | BPF_K, k = 0
    program = struct.pack("HL", 1, ctypes.addressof(drop_all))  # struct sock_fprog
    with contextlib.suppress(OSError):
        listener.setsockopt(socket.SOL_SOCKET, SO_ATTACH_FILTER, program)


def raise_open_file_limit() -> None:
    """Raise this process's soft limit of open files to its hard limit (as Go programs do at start):
    a soft limit of 1024 would cap the connections a server holds far below what it can serve."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft != hard:
        with contextlib.suppress(ValueError, OSError):
            resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))


def connection_cap(wanted: int) -> int:
    """At most `wanted` HTTP connections, and never so many that the process would run out of file
    descriptors: then accept() fails, and with it the readiness probe and gRPC health."""
    soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft == resource.RLIM_INFINITY:
        return wanted
    return max(1, min(wanted, soft - RESERVED_FDS))


class HttpServer(uvicorn.Server):
    """uvicorn without its own signal handlers (main() owns SIGTERM and SIGINT), with an accept
    path of its own, and whose shutdown answers every connection the kernel accepted."""

    def __init__(self, config: uvicorn.Config) -> None:
        super().__init__(config)
        self._acceptors: list[socket.socket] = []  # a dup of each listener, read by _accept_waiting
        self._connecting: set[asyncio.Task[object]] = set()

    @contextlib.contextmanager
    def capture_signals(self) -> Generator[None, None, None]:
        """Leave SIGTERM and SIGINT to main()."""
        yield

    async def startup(self, sockets: list[socket.socket] | None = None) -> None:
        """uvicorn's startup, then a reader on each listener that accepts every waiting connection.

        libuv (under uvloop) accepts one connection per event-loop iteration (libuv 1.45, "unix:
        don't accept() connections in a loop"), and asyncio up to 100. When the loop is busy, an
        iteration takes tens of milliseconds: 512 clients that connect within a second then wait
        in the listen backlog for seconds, and a health probe's fresh connection behind them times
        out. The reader takes up to ACCEPT_BATCH waiting connections each time the listener is
        readable (the listener stays readable while more wait)."""
        await super().startup(sockets)
        loop = asyncio.get_running_loop()
        for server in getattr(self, "servers", []):
            for listener in server.sockets:
                acceptor = listener.dup()  # the same listening socket, already non-blocking
                acceptor.setblocking(False)
                loop.add_reader(acceptor.fileno(), self._accept_waiting, acceptor)
                self._acceptors.append(acceptor)

    def _accept_waiting(self, acceptor: socket.socket) -> None:
        loop = asyncio.get_running_loop()
        for _ in range(ACCEPT_BATCH - len(self._connecting)):  # those not yet handed to uvicorn count
            try:
                connection, _ = acceptor.accept()
            except (BlockingIOError, InterruptedError):
                return  # the backlog is empty (or the loop's own accept took the last one)
            except OSError as err:  # ECONNABORTED, or out of file descriptors (EMFILE)
                log.warning("accepting a connection failed: %s", err)
                if err.errno in (errno.EMFILE, errno.ENFILE):  # the listener stays readable: rest
                    loop.remove_reader(acceptor.fileno())
                    loop.call_later(ACCEPT_RETRY_S, self._resume_accepting, acceptor)
                return
            connection.setblocking(False)
            if connection.family in (socket.AF_INET, socket.AF_INET6):
                connection.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            task = loop.create_task(
                loop.connect_accepted_socket(self._create_protocol, connection, ssl=self.config.ssl)
            )
            self._connecting.add(task)
            task.add_done_callback(self._connecting.discard)

    def _resume_accepting(self, acceptor: socket.socket) -> None:
        if acceptor in self._acceptors:  # not closed by shutdown meanwhile
            asyncio.get_running_loop().add_reader(acceptor.fileno(), self._accept_waiting, acceptor)

    def _stop_accepting(self) -> None:
        loop = asyncio.get_running_loop()
        for acceptor in self._acceptors:
            loop.remove_reader(acceptor.fileno())
            acceptor.close()
        self._acceptors.clear()

    async def shutdown(self, sockets: list[socket.socket] | None = None) -> None:
        """uvicorn's shutdown would reset connections still in the listen backlog when it closes
        the listener, and close accepted connections whose request it has not read yet: their
        clients saw the connection accepted and lose the request. Stop handshakes, accept the
        backlog, close the listener, and wait for the first request of fresh connections."""
        loop = asyncio.get_running_loop()
        self._stop_accepting()
        if self._connecting:  # connections it accepted become uvicorn's before the drain below
            await asyncio.wait(list(self._connecting))
        backlog: list[socket.socket] = []
        for server in self.servers:
            for listener in server.sockets:
                with listener.dup() as sock:  # the same listening socket, already non-blocking
                    stop_handshakes(sock)
                    with contextlib.suppress(OSError):  # EAGAIN: the backlog is empty
                        while True:
                            backlog.append(sock.accept()[0])
            server.close()
        for sock in backlog:
            await loop.connect_accepted_socket(self._create_protocol, sock, ssl=self.config.ssl)
        deadline = loop.time() + min(FIRST_REQUEST_WAIT_S, self.config.timeout_graceful_shutdown or 0)
        # `cycle` is None until a connection's first request arrives (h11 and httptools alike).
        while any(getattr(c, "cycle", 0) is None for c in self.server_state.connections):
            if loop.time() > deadline:
                break
            await asyncio.sleep(0.005)
        await super().shutdown(sockets)

    def _create_protocol(self) -> asyncio.Protocol:
        """The protocol uvicorn's startup() gives each connection it accepts."""
        return self.config.http_protocol_class(  # type: ignore[call-arg]
            config=self.config, server_state=self.server_state, app_state=self.lifespan.state
        )


def http_config(app: FastAPI, settings: Settings) -> uvicorn.Config:
    """uvicorn's configuration of the HTTP server: its connections guarded (service/http_protocol.py),
    over TLS when tls_cert is set (requiring a client certificate when tls_client_ca is)."""
    limits = ConnectionLimits(
        header_timeout_s=settings.http_header_timeout_s,
        max_header_bytes=settings.http_max_header_bytes,
        body_timeout_s=settings.http_body_timeout_s,
        body_min_rate=settings.http_body_min_rate,
        max_connections=connection_cap(settings.http_max_connections),
    )
    ca = settings.tls_client_ca
    return uvicorn.Config(
        app,
        host=settings.host,
        port=settings.http_port,
        http=guarded_protocol(limits),
        log_level=settings.log_level,
        access_log=settings.log_level == "debug",  # one line per request costs more than a lift
        timeout_graceful_shutdown=max(1, round(settings.shutdown_grace_s)),
        lifespan="off",
        ssl_certfile=settings.tls_cert,
        ssl_keyfile=settings.tls_key,
        ssl_cert_reqs=ssl.CERT_REQUIRED if ca is not None else ssl.CERT_NONE,
        ssl_ca_certs=ca,
    )
