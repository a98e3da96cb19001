"""Composition root: Settings -> Lifters -> Metrics -> Engines (one per model) -> HTTP app + gRPC
server, and main()."""

from __future__ import annotations

import argparse
import gc
import logging
import signal
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from types import FrameType

import uvicorn
from fastapi import FastAPI
from prometheus_client import CollectorRegistry
from pydantic import ValidationError

from repnet.core.errors import ModelLoadError
from repnet.core.inputs import Limits
from repnet.runtime.batchers import LiftBatcher
from repnet.runtime.catalog import Catalog
from repnet.runtime.lifter import Lifter
from repnet.runtime.loading import file_sha256, known_poses, serves_under
from repnet.runtime.plans import TemporalModels
from repnet.server.auth import ApiKeys
from repnet.server.config import Settings, trusted_hosts
from repnet.server.grpc.server import GrpcServer, create_server, read_tls
from repnet.server.http.api import create_app
from repnet.server.http.server import HttpServer, http_config, raise_open_file_limit
from repnet.server.metrics import Metrics
from repnet.server.startup import load_dir_lifters, load_lifter, load_temporal
from repnet.server.workers import (
    SERVE,
    Peers,
    Supervisor,
    allowed_cpus,
    follow_supervisor,
    pin_worker,
    reuse_port_socket,
    usable_cpus,
    worker_cpus,
)

__all__ = ["Service", "build_service", "known_poses", "load_lifter", "load_temporal", "main"]

log = logging.getLogger("repnet.server")


def limits_of(settings: Settings) -> Limits:
    """The input limits of `settings`."""
    return Limits(
        max_request_poses=settings.max_request_poses,
        min_visible_joints=settings.min_visible_joints,
        confidence_threshold=settings.confidence_threshold,
        max_coordinate=settings.max_coordinate,
        max_temporal_poses=settings.max_temporal_poses,
    )


@dataclass
class Service:
    """Both servers on one LiftBatcher per model (one onnxruntime session each), and their shutdown."""

    settings: Settings
    models: Catalog
    metrics: Metrics
    app: FastAPI
    grpc_server: GrpcServer
    http: uvicorn.Server
    temporal: TemporalModels | None = None
    peers: Peers | None = None  # the other workers of a supervised service (server.workers)
    _stopping: threading.Event = field(default_factory=threading.Event)
    _grpc_stopped: threading.Event | None = None
    _delay: threading.Timer | None = None

    @property
    def engine(self) -> LiftBatcher:
        """The default model's batcher."""
        return self.models.default_engine

    def begin_shutdown(self) -> None:
        """Report not ready (HTTP /readyz 503, gRPC health NOT_SERVING); after shutdown_delay_s
        (time for load balancers to notice) stop accepting and drain."""
        if self._stopping.is_set():
            return
        self._stopping.set()
        log.info("shutting down: draining in-flight requests (grace %.1f s)", self.settings.shutdown_grace_s)
        if self.peers is not None:
            self.peers.mark_ready(False)
        self.models.stop_serving()
        self.grpc_server.health.enter_graceful_shutdown()
        if self.settings.shutdown_delay_s > 0:
            self._delay = threading.Timer(self.settings.shutdown_delay_s, self.stop_accepting)
            self._delay.daemon = True
            self._delay.start()
        else:
            self.stop_accepting()

    def stop_accepting(self) -> None:
        """Refuse new calls and connections; in-flight ones get shutdown_grace_s to finish."""
        if self._delay is not None:
            self._delay.cancel()
        if self._grpc_stopped is None:
            self._grpc_stopped = self.grpc_server.stop(self.settings.shutdown_grace_s)
        self.http.should_exit = True

    def run(self) -> int:
        """Serve until begin_shutdown, drain, then return the exit status."""
        # What start-up made (modules, models' metadata, the proto classes) lives as long as the
        # process: out of the collector's sight, so that a full collection while serving walks only
        # what requests made (start-up's ~88,000 objects took 19-28 ms to walk on 2 cores: a stall of every
        # stream at once).
        gc.collect()
        gc.freeze()
        self.grpc_server.start()
        log.info(
            "models %s: HTTP on %s:%d, gRPC on %s:%d",
            self.models.known(),
            self.settings.host,
            self.settings.http_port,
            self.settings.host,
            self.grpc_server.port,
        )
        status = 0
        sockets = None
        if self.peers is not None:  # a worker: the port is shared with the others (SO_REUSEPORT)
            sockets = [reuse_port_socket(self.settings.host, self.settings.http_port)]
            threading.Thread(target=self._announce, name="repnet-ready", daemon=True).start()
        try:
            self.http.run(sockets=sockets)  # returns once should_exit is set and HTTP requests have drained
        except SystemExit as exit_:  # uvicorn exits when it cannot bind its port
            status = exit_.code if isinstance(exit_.code, int) and exit_.code else 1
        if not self._stopping.is_set():  # uvicorn stopped on its own
            status = status or 1
            self.begin_shutdown()
        self.stop_accepting()  # in case uvicorn failed before the shutdown delay ran out
        if self._grpc_stopped is not None:
            self._grpc_stopped.wait(self.settings.shutdown_grace_s + 1)
        self.models.close(self.settings.shutdown_grace_s)
        for temporal in self.temporal.engines.values() if self.temporal is not None else ():
            temporal.close(self.settings.shutdown_grace_s)
        log.info("stopped; requests answered: %s", answered_requests(self.metrics))
        return status

    def _announce(self) -> None:
        """A worker: ready once its HTTP server serves; gRPC health SERVING once every worker is."""
        assert self.peers is not None
        while not self.http.started and not self._stopping.is_set():
            time.sleep(0.02)
        if self._stopping.is_set():
            return
        self.peers.mark_ready(True)
        while not self.peers.all_ready() and not self._stopping.is_set():
            time.sleep(0.05)
        if not self._stopping.is_set():
            self.grpc_server.health.set(True)


def answered_requests(metrics: Metrics) -> str:
    """'transport method outcome=count' for every lift request counted since start."""
    counts = [
        f"{s.labels['transport']} {s.labels['method']} {s.labels['outcome']}={s.value:.0f}"
        for family in metrics.registry.collect()
        if family.name == "repnet_requests"
        for s in family.samples
        if s.name == "repnet_requests_total"
    ]
    return ", ".join(counts) or "none"


def build_batcher(lifter: Lifter, metrics: Metrics, settings: Settings) -> LiftBatcher:
    """The batcher of `lifter` with the batching settings."""
    return LiftBatcher(
        lifter,
        metrics,
        max_batch=settings.max_batch,
        max_wait_s=settings.max_wait_ms / 1000,
        queue_size=settings.queue_size,
        company_wait_s=settings.company_wait_ms / 1000,
    )


def build_app(
    engine: LiftBatcher | Catalog,
    metrics: Metrics,
    settings: Settings,
    temporal: TemporalModels | None = None,
    api_keys: ApiKeys | None = None,
) -> FastAPI:
    """The HTTP app on `engine` (and the temporal models) with the HTTP settings."""
    return create_app(
        engine,
        metrics,
        limits_of(settings),
        temporal=temporal,
        max_body_bytes=settings.max_body_bytes,
        ui=settings.ui,
        max_in_flight=settings.http_max_in_flight,
        api_keys=api_keys,
        allowed_hosts=trusted_hosts(settings),
    )


def build_grpc_server(
    engine: LiftBatcher | Catalog,
    metrics: Metrics,
    settings: Settings,
    temporal: TemporalModels | None = None,
    api_keys: ApiKeys | None = None,
    reuse_port: bool = False,
) -> GrpcServer:
    """The gRPC server on `engine` (and the temporal models; bound to host:grpc_port, not started)
    with the gRPC settings (`reuse_port`: a worker's, sharing the port with the others)."""
    return create_server(
        engine,
        metrics,
        limits_of(settings),
        f"{settings.host}:{settings.grpc_port}",
        temporal=temporal,
        tls=read_tls(settings.tls_cert, settings.tls_key, settings.tls_client_ca),
        api_keys=api_keys,
        workers=settings.grpc_workers,
        max_streams=settings.grpc_max_streams,
        max_client_streams=settings.grpc_max_streams_per_client or max(1, settings.grpc_max_streams // 2),
        stream_idle_timeout_s=settings.stream_idle_timeout_s,
        max_message_bytes=settings.max_body_bytes,
        stream_window_poses=settings.stream_window_poses,
        reuse_port=reuse_port,
    )


def build_service(settings: Settings, lifter: Lifter | None = None) -> Service:
    """Load the default model (unless given), the models of model_dir and the temporal models, and
    wire both servers; nothing is started yet."""
    lifter = lifter or load_lifter(settings)
    lifters = [lifter, *load_dir_lifters(settings, lifter)]
    metrics = Metrics(CollectorRegistry())
    metrics.set_models([(m.info.model_id, m.info.skeleton) for m in lifters])
    engines = {m.info.model_id: build_batcher(m, metrics, settings) for m in lifters}
    temporal = load_temporal(settings, lifter, metrics)
    sha256 = {m.info.model_id: file_sha256(m.path) for m in lifters}
    peers = Peers.from_env()  # a supervised worker's (server.workers)
    ready = None if peers is None else peers.all_ready
    temporal_models: set[str] = set()
    if temporal is not None:  # the model they were loaded with, and those adapted from their base
        temporal_models = {lifter.info.model_id} | {
            m.info.model_id
            for m in lifters[1:]
            if all(
                serves_under(e.lifter.base_model_sha256, sha256[m.info.model_id], m.info.metadata)
                for e in temporal.engines.values()
            )
        }
    models = Catalog(engines, frozenset(temporal_models), sha256, ready)
    api_keys = None if settings.api_keys_file is None else ApiKeys.read(settings.api_keys_file)
    app = build_app(models, metrics, settings, temporal, api_keys)
    grpc_server = build_grpc_server(models, metrics, settings, temporal, api_keys, peers is not None)
    http = HttpServer(http_config(app, settings))
    return Service(settings, models, metrics, app, grpc_server, http, temporal, peers)


def parse_settings(argv: Sequence[str] | None) -> Settings:
    """Flags override REPNET_* variables, which override the defaults; one flag per field."""
    parser = argparse.ArgumentParser(
        prog="repnet serve",
        description="RepNet pose-lifting server "
        "(HTTP and gRPC). Every flag can also be set as REPNET_<FIELD>.",
    )
    for name, info in Settings.model_fields.items():
        parser.add_argument(
            f"--{name.replace('_', '-')}",
            dest=name,
            metavar=name.upper(),
            # argparse formats help with %: a literal one (e.g. "+20 %") must be doubled.
            help=f"{info.description or name} (default: {info.default})".replace("%", "%%"),
        )
    args = parser.parse_args(argv)
    return Settings(**{k: v for k, v in vars(args).items() if v is not None})


def main(
    argv: Sequence[str] | None = None,
    *,
    module: Sequence[str] = SERVE,
    lifter: Callable[[Settings], Lifter] = load_lifter,
) -> int:
    """`python -m repnet serve`: parse the settings, load the model, serve until a signal; the exit
    status. `module` and `lifter`: what the workers run and how the model is loaded, for a program
    that serves like `repnet serve` (bench.ceiling: its workers, the model taken out)."""
    try:
        settings = parse_settings(argv)
    except ValidationError as err:
        print(f"invalid settings:\n{err}", file=sys.stderr)
        return 2
    peers = Peers.from_env()
    if peers is not None:
        follow_supervisor()
        pin_worker()  # before any thread of the models or the servers starts
    worker = "" if peers is None else f"[worker {peers.index}] "
    logging.basicConfig(
        level=settings.log_level.upper(), format=f"%(asctime)s %(levelname)s {worker}%(name)s: %(message)s"
    )
    usable = usable_cpus()
    count = settings.workers or usable
    if peers is None and count > 1:  # the supervisor: the workers do the serving
        ports = (settings.http_port, settings.grpc_port)
        flags = list(sys.argv[1:] if argv is None else argv)
        cpus = worker_cpus(count, settings.cpu_affinity, allowed_cpus(), usable)
        try:
            supervisor = Supervisor(
                flags, count, settings.host, ports, settings.shutdown_grace_s, module, cpus
            )
        except OSError as err:  # a port is taken
            log.error("cannot start: %s", err)
            return 1
        return supervisor.run()
    raise_open_file_limit()
    try:
        service = build_service(settings, lifter(settings))
    except (ModelLoadError, OSError, ValueError) as err:  # ValueError: an API keys file without keys
        if peers is None:
            log.error("cannot start: %s", err)
        else:  # the supervisor says it, once for the service
            peers.failed(str(err))
        return 1
    return serve(service)


def serve(service: Service) -> int:
    """Run `service` until SIGTERM or SIGINT, drain it and return the exit status (main thread only)."""

    def on_signal(signum: int, frame: FrameType | None) -> None:
        log.info("received %s", signal.Signals(signum).name)
        service.begin_shutdown()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    return service.run()
