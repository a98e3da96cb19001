"""Metrics: every Prometheus metric of the service, built on a registry it is given."""

from __future__ import annotations

import asyncio
import contextlib
import os
import time
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, multiprocess
from prometheus_client.metrics_core import Metric

from repnet.core.errors import InvalidKeypoints, ModelNotReady, ModelOutputError, Overloaded, Violation

# Latency buckets (s): fine below 10 ms where a single pose should land, coarse above.
LATENCY_BUCKETS = (
    0.0005,
    0.001,
    0.002,
    0.003,
    0.005,
    0.0075,
    0.01,
    0.025,
    0.05,
    0.1,
    0.25,
    0.5,
    1.0,
    2.5,
    5.0,
    10.0,
)
BATCH_BUCKETS = (1, 2, 4, 8, 16, 32, 64, 128, 256, 512, 1024, 2048)
# Plausibility is a percentile among real poses: deciles, plus the tails where implausible poses sit.
PLAUSIBILITY_BUCKETS = (0.01, 0.05, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0)

OK, INVALID, OVERLOADED, UNAVAILABLE, ERROR = "ok", "invalid", "overloaded", "unavailable", "error"
# The client cancelled the call, its deadline passed, or it went away before its request was read.
CANCELLED = "cancelled"
UNAUTHENTICATED = "unauthenticated"  # no valid API key (REPNET_API_KEYS_FILE)


def outcome_of(error: BaseException | None) -> str:
    """The `outcome` label for a request that ended with `error` (None: it succeeded)."""
    if error is None:
        return OK
    if isinstance(error, InvalidKeypoints):
        return INVALID
    if isinstance(error, Overloaded):
        return OVERLOADED
    if isinstance(error, ModelNotReady):
        return UNAVAILABLE
    if isinstance(error, asyncio.CancelledError):  # grpc.aio cancels a call's task (client, deadline)
        return CANCELLED
    return ERROR


@dataclass
class Tracked:
    """A request being measured; an adapter may set the outcome when it handles an error itself."""

    outcome: str | None = None


class Metrics:
    """The service's metrics; documented in docs/API.md, section Metrics."""

    def __init__(self, registry: CollectorRegistry) -> None:
        self.registry = registry
        labels = ["transport", "method", "outcome"]
        self.requests = Counter(
            "repnet_requests",
            "Lift requests (HTTP requests, unary RPCs, stream frames) by outcome.",
            labels,
            registry=registry,
        )
        self.request_seconds = Histogram(
            "repnet_request_duration_seconds",
            "Time from receiving a lift request to its answer.",
            labels,
            buckets=LATENCY_BUCKETS,
            registry=registry,
        )
        self.rejected = Counter(
            "repnet_rejected_inputs",
            "Rejected inputs by reason (one count per reason per request).",
            ["transport", "reason"],
            registry=registry,
        )
        self.in_flight = Gauge(
            "repnet_in_flight_requests",
            "Lift requests and stream frames being handled now.",
            ["transport"],
            multiprocess_mode="livesum",
            registry=registry,
        )
        self.open_streams = Gauge(
            "repnet_open_streams",
            "LiftStream calls open now.",
            multiprocess_mode="livesum",
            registry=registry,
        )
        self.idle_streams_closed = Counter(
            "repnet_idle_streams_closed",
            "LiftStream calls closed by the server after stream_idle_timeout_s without a frame.",
            registry=registry,
        )
        self.open_tracks = Gauge(
            "repnet_open_tracks",
            "Tracks of LiftStream calls open now.",
            multiprocess_mode="livesum",
            registry=registry,
        )
        self.track_state_bytes = Gauge(
            "repnet_track_state_bytes",
            "Bytes of frames the open tracks hold now.",
            multiprocess_mode="livesum",
            registry=registry,
        )
        self.model_output_errors = Counter(
            "repnet_model_output_errors",
            "Poses for which the model produced non-finite output (answered 500 / INTERNAL).",
            registry=registry,
        )
        self.parse_seconds = Histogram(
            "repnet_request_parse_seconds",
            "Time to read, parse and check a lift request's poses and convert them to the model's "
            "joints (HTTP: from the request's arrival, so a slow upload shows; gRPC Lift: after "
            "protobuf decoding), valid or not.",
            ["transport"],
            buckets=LATENCY_BUCKETS,
            registry=registry,
        )
        self.queue_wait_seconds = Histogram(
            "repnet_batch_queue_wait_seconds",
            "Time a chunk of poses waited in its model's batch queue.",
            ["model", "transport"],
            buckets=LATENCY_BUCKETS,
            registry=registry,
        )
        self.inference_seconds = Histogram(
            "repnet_inference_seconds",
            "Time of one model run (a whole batch): onnxruntime, masking and the non-finite check.",
            ["model"],
            buckets=LATENCY_BUCKETS,
            registry=registry,
        )
        self.batch_size = Histogram(
            "repnet_batch_size_poses",
            "Poses per onnxruntime run, after dynamic batching.",
            ["model"],
            buckets=BATCH_BUCKETS,
            registry=registry,
        )
        self.plausibility = Histogram(
            "repnet_pose_plausibility_ratio",
            "Plausibility of each lifted pose (the model's calibrated pose score in [0, 1]); "
            "empty when the model has no plausibility output.",
            ["model"],
            buckets=PLAUSIBILITY_BUCKETS,
            registry=registry,
        )
        self.queue_depth = Gauge(
            "repnet_batch_queue_poses",
            "Poses waiting in a model's batch queue now.",
            ["model"],
            multiprocess_mode="livesum",
            registry=registry,
        )
        self.lifted_poses = Counter(
            "repnet_lifted_poses",
            "Poses lifted by a model (every run's poses, counted when the run ends).",
            ["model", "transport"],
            registry=registry,
        )
        self.model_info = Gauge(
            "repnet_model_info",
            "The loaded single-frame models (value 1 each), labelled by id and skeleton; default "
            "is true for the model a request that names none gets.",
            ["model_id", "skeleton", "default"],
            multiprocess_mode="livemax",
            registry=registry,
        )

    def scraped(self) -> CollectorRegistry:
        """What GET /metrics reports: this registry; with workers (prometheus_client's multiprocess
        folder set), every worker's metrics as one, read from the folder."""
        folder = os.environ.get("PROMETHEUS_MULTIPROC_DIR")
        if not folder:
            return self.registry
        return worker_metrics(folder)

    def set_model(self, model_id: str, skeleton: str) -> None:
        """Label repnet_model_info with the one loaded model (the default)."""
        self.set_models([(model_id, skeleton)])

    def set_models(self, models: Sequence[tuple[str, str]]) -> None:
        """Label repnet_model_info with the loaded models (model_id, skeleton), the default first.
        Only these ids ever label a metric: the `model` label's values are bounded by the models
        loaded at start, never by what requests name."""
        if not os.environ.get("PROMETHEUS_MULTIPROC_DIR"):  # a worker's values cannot be cleared
            self.model_info.clear()  # (prometheus_client warns): a worker sets them once, at start
        for k, (model_id, skeleton) in enumerate(models):
            self.model_info.labels(model_id=model_id, skeleton=skeleton, default=str(k == 0).lower()).set(1)

    def batch_queued(self, model: str, depth: int) -> None:
        """`depth` poses wait for a run of `model` (runtime.batcher.BatchMetrics)."""
        self.queue_depth.labels(model=model).set(depth)

    def batch_waited(self, model: str, transport: str, seconds: float) -> None:
        """A request's chunk waited `seconds` in the queue before its run."""
        self.queue_wait_seconds.labels(model=model, transport=transport).observe(seconds)

    def batch_ran(self, model: str, seconds: float, size: int) -> None:
        """A run of `size` poses took `seconds`."""
        self.inference_seconds.labels(model=model).observe(seconds)
        self.batch_size.labels(model=model).observe(size)

    def poses_lifted(self, model: str, transport: str, count: int) -> None:
        """`count` poses of a `transport` request were lifted."""
        self.lifted_poses.labels(model=model, transport=transport).inc(count)

    def observe_plausibility(self, model: str, values: Iterable[float]) -> None:
        """One observation per pose (N,): a Python loop, run only for models with the output."""
        histogram = self.plausibility.labels(model=model)
        for value in values:
            histogram.observe(float(value))

    def reject(self, transport: str, violations: Sequence[Violation]) -> None:
        """Count a rejected input: once per reason it broke."""
        for code in sorted({v.code for v in violations}):
            self.rejected.labels(transport=transport, reason=code).inc()

    def count_error(self, transport: str, error: BaseException) -> None:
        """Count what an error answer says beyond its outcome: the reasons of rejected input, the
        poses the model failed on (counted when answered, on every transport)."""
        if isinstance(error, InvalidKeypoints):
            self.reject(transport, error.violations)
        elif isinstance(error, ModelOutputError):
            self.model_output_errors.inc(len(error.rows))

    @contextmanager
    def parsing(self, transport: str, started: float | None = None) -> Iterator[None]:
        """Time a request's input rules for the parse histogram, from `started` (time.perf_counter(),
        default now: HTTP passes when the body began to arrive), valid or not."""
        started = time.perf_counter() if started is None else started
        try:
            yield
        finally:
            self.parse_seconds.labels(transport=transport).observe(time.perf_counter() - started)

    def finish(self, transport: str, method: str, outcome: str, seconds: float) -> None:
        """Count one finished request and its latency."""
        self.requests.labels(transport=transport, method=method, outcome=outcome).inc()
        self.request_seconds.labels(transport=transport, method=method, outcome=outcome).observe(seconds)

    @contextmanager
    def track(self, transport: str, method: str) -> Iterator[Tracked]:
        """Measure one request: in-flight while inside, then count, time and classify it.

        The outcome comes from the exception that leaves the block (re-raised), or from
        `Tracked.outcome` when the adapter set it; rejected inputs are counted by reason.
        """
        tracked = Tracked()
        gauge = self.in_flight.labels(transport=transport)
        gauge.inc()
        start = time.perf_counter()
        error: BaseException | None = None
        try:
            yield tracked
        except BaseException as err:
            error = err
            raise
        finally:
            gauge.dec()
            if error is not None:
                self.count_error(transport, error)
            outcome = tracked.outcome or outcome_of(error)
            self.finish(transport, method, outcome, time.perf_counter() - start)

    def set_tracks(self, tracks: int, nbytes: int) -> None:
        """The open tracks and the bytes they hold (tracks.TrackBudget's on_change)."""
        self.open_tracks.set(tracks)
        self.track_state_bytes.set(nbytes)


class _WorkerFiles:
    """Every worker's metrics from prometheus_client's multiprocess folder, as its own collector
    reads them, past the files a worker is still creating: a worker opens its file empty, then
    sizes it, and one empty file failed the whole read (a scrape, or the supervisor's last line,
    while a worker started)."""

    def __init__(self, folder: str) -> None:
        self.folder = Path(folder)

    def collect(self) -> Iterable[Metric]:
        """The merged metrics of every file that holds at least its header."""
        files = []
        for path in self.folder.glob("*.db"):
            with contextlib.suppress(OSError):  # a dead worker's gauge file may go meanwhile
                if path.stat().st_size >= 8:
                    files.append(str(path))
        merge = multiprocess.MultiProcessCollector.merge
        merged: Iterable[Metric] = merge(files, accumulate=True)  # type: ignore[no-untyped-call]
        return merged


def worker_metrics(folder: str) -> CollectorRegistry:
    """A registry of every worker's metrics, read from `folder` (prometheus_client's multiprocess
    folder) at each collect."""
    registry = CollectorRegistry()
    registry.register(_WorkerFiles(folder))
    return registry
