"""Settings of the service: environment variables with the REPNET_ prefix, then flags."""

from __future__ import annotations

import ipaddress
from pathlib import Path
from typing import Literal

from pydantic import Field, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from repnet.core.inputs import Limits
from repnet.runtime.batcher import MAX_BATCH
from repnet.runtime.loading import BUNDLED_CAUSAL, BUNDLED_MODEL, BUNDLED_OFFLINE
from repnet.runtime.session import SessionOptions


class Settings(BaseSettings):
    """Everything an operator can set, and the only place a default lives. app.main creates it once
    and passes it down (Lifter, LiftBatcher, Limits, the HTTP app and the gRPC server take no defaults)."""

    model_config = SettingsConfigDict(env_prefix="REPNET_", extra="ignore", frozen=True)

    model_path: Path = Field(default=BUNDLED_MODEL, description="ONNX model file: the default model")
    model_dir: Path | None = Field(
        default=None,
        description="folder of more single-frame ONNX models (`*.onnx`, any case) served beside "
        "`model_path`, which stays the default; a request names one by its `model_id` (`GET /v1/models`). "
        "Each is checked at start: one that fails stops the start (see [Several models](#several-models))",
    )
    host: str = Field(
        default="127.0.0.1",
        description="address both servers bind to: this machine only, so that `repnet serve` on a "
        "workstation is not reachable from its network; the container image sets `0.0.0.0` so that the "
        "ports it publishes reach it (see [Container](#container-and-deployment))",
    )
    allowed_hosts: str | None = Field(
        default=None,
        description="`Host` header names the HTTP server answers, comma-separated (`*.example.com`: its "
        "subdomains; `*`: any); another gets 400 `Invalid host header`. Unset: `localhost`, `127.0.0.1` and "
        "`[::1]` while `host` is a loopback address (so that a web page elsewhere cannot reach the service "
        "through DNS rebinding), any host otherwise (on a network, set it; behind a proxy that checks "
        "`Host`, `*`)",
    )
    http_port: int = Field(default=8000, ge=0, le=65535, description="HTTP port (0: any free port)")
    grpc_port: int = Field(default=50051, ge=0, le=65535, description="gRPC port (0: any free port)")
    intra_op_threads: int = Field(
        default=SessionOptions.intra_op_threads,
        ge=0,
        description="onnxruntime threads per run (0: one per core; with several workers, unless set: the "
        "usable CPUs shared out between them)",
    )
    inter_op_threads: int = Field(
        default=SessionOptions.inter_op_threads, ge=0, description="onnxruntime inter-op threads"
    )
    intra_op_spinning: bool = Field(
        default=SessionOptions.intra_op_spinning,
        description="onnxruntime threads spin between runs (faster single runs on idle cores; off "
        "leaves the CPU to the server's own threads, +20 % stream throughput on 2 cores: "
        "[BENCHMARKS](BENCHMARKS.md))",
    )
    workers: int = Field(
        default=0,
        ge=0,
        description="server processes sharing the HTTP and gRPC ports, each with its own models, "
        "batchers and streams; the limits below are per worker (0: one per CPU this process may use: "
        "its CPU affinity, and a container's CPU limit; see [Workers](#workers))",
    )
    cpu_affinity: Literal["auto", "on", "off"] = Field(
        default="auto",
        description="with several workers, each worker's threads run on CPUs of its own: worker i on "
        "the i-th of the CPUs this process may use, or its i-th share of them when there are more "
        "CPUs than workers (`on`); `auto`: only when the workers are as many as those CPUs and no "
        "container CPU limit is below them (the workers own the CPUs: a machine or a cpuset of "
        "their own); `off`: the kernel places every thread (see [Workers](#workers))",
    )
    grpc_workers: int = Field(
        default=32,
        ge=1,
        description="most gRPC `Lift` calls in progress at once; beyond: `RESOURCE_EXHAUSTED` (streams "
        "have their own limit, health checks none)",
    )
    grpc_max_streams: int = Field(
        default=64, ge=1, description="most `LiftStream` calls open at once; beyond: `RESOURCE_EXHAUSTED`"
    )
    grpc_max_streams_per_client: int = Field(
        default=0,
        ge=0,
        description="most `LiftStream` calls one client has open at once (a client: its API key, or "
        "its address when the service has no keys); beyond: `RESOURCE_EXHAUSTED`. With the streams' own "
        "limit on tracks, one client holds at most this many times `stream_max_tracks` tracks (0: half "
        "of `grpc_max_streams`, at least 1)",
    )
    stream_idle_timeout_s: float = Field(
        default=60.0,
        gt=0,
        description="a `LiftStream` with nothing in progress that sends no frame for this long is "
        "closed with `DEADLINE_EXCEEDED`",
    )
    http_max_in_flight: int = Field(
        default=128,
        ge=1,
        description="most `POST /lift` requests in progress at once (a request counts once its body has "
        "arrived); beyond: 503 with `Retry-After` at once (health, readiness and metrics are never refused)",
    )
    http_header_timeout_s: float = Field(
        default=10.0,
        gt=0,
        description="a connection whose request line and headers are not complete this long after "
        "it opened (or after its request's first byte) is closed (408 once part of a request came)",
    )
    http_max_header_bytes: int = Field(
        default=64 * 1024, ge=1024, description="largest request line and headers; beyond: 431, closed"
    )
    http_body_timeout_s: float = Field(
        default=10.0,
        gt=0,
        description="time a request body has to arrive, plus 1 s per `http_body_min_rate` bytes "
        "received; beyond: 408, closed",
    )
    http_body_min_rate: int = Field(
        default=16 * 1024,
        ge=1,
        description="bytes per second a body must average after the first `http_body_timeout_s`",
    )
    http_max_connections: int = Field(
        default=1000,
        ge=1,
        description="most HTTP connections open at once (never more than the limit of open files less 128); "
        "beyond, the connection idle longest is closed, or the new one when none is idle",
    )
    tls_cert: Path | None = Field(
        default=None, description="PEM certificate chain: serve HTTPS and gRPC over TLS (with `tls_key`)"
    )
    tls_key: Path | None = Field(default=None, description="PEM private key of `tls_cert`")
    tls_client_ca: Path | None = Field(
        default=None,
        description="PEM CA certificates: require a client certificate signed by one (mutual TLS)",
    )
    api_keys_file: Path | None = Field(
        default=None,
        description="file of API keys, one per line (`#` comments): `/lift`, `/v1/*` and both gRPC methods "
        "then need one (HTTP `Authorization: Bearer KEY`, gRPC `authorization` metadata)",
    )
    max_batch: int = Field(default=MAX_BATCH, ge=1, description="most poses in one onnxruntime run")
    max_wait_ms: float = Field(
        default=4.0,
        ge=0,
        description="the batching window at full load: the longest a request waits for others to join "
        "its batch. The window follows the load: a batcher busy under a quarter of its time runs a "
        "request at once, a busier one lets it wait up to this, in proportion (0: never wait)",
    )
    company_wait_ms: float = Field(
        default=12.0,
        ge=0,
        description="the longest a request waits for a client that is expected to send within it (a "
        "paced camera's next frame, from the gaps between its last ones) to join its run, however busy "
        "the batcher is, until 4 poses wait: cameras share runs instead of each paying a run per frame. "
        "A client that waits for each answer is never waited for; under load (work queued during the "
        "last run) the batching window applies instead (0: never wait)",
    )
    queue_size: int = Field(
        default=8192,
        ge=1,
        description="most poses waiting for a run; beyond: 503 / `RESOURCE_EXHAUSTED`. One client (an HTTP "
        "or gRPC connection) holds at most a quarter of it (at least `max_batch`); beyond, its request is "
        "refused the same way and its stream waits, while the others' requests still fit (see "
        "[Fair share](#fair-share-between-clients))",
    )
    max_request_poses: int = Field(
        default=Limits.max_request_poses, ge=1, description="most poses in one request"
    )
    max_body_bytes: int = Field(
        default=4 * 1024 * 1024, ge=1024, description="largest HTTP body / gRPC message"
    )
    min_visible_joints: int = Field(
        default=Limits.min_visible_joints, ge=2, le=17, description="fewest visible model joints per pose"
    )
    confidence_threshold: float = Field(
        default=Limits.confidence_threshold,
        ge=0,
        le=1,
        description="default: a joint with confidence below it counts as missing",
    )
    max_coordinate: float = Field(
        default=Limits.max_coordinate, gt=0, description="largest accepted |x| or |y| in pixels"
    )
    stream_window_poses: int = Field(
        default=1024,
        ge=1,
        description="poses of one stream in flight at once, read and not yet answered (a frame counts its "
        "people; the last frame read may pass it, so a stream holds fewer than this plus one frame of "
        "`max_request_poses`); the stream is read no further until some are answered. Replaces "
        "`REPNET_STREAM_WINDOW` (frames)",
    )
    temporal: bool = Field(
        default=True,
        description="load the temporal models (tracked poses of streams and of temporal requests); false: "
        "every pose is lifted alone",
    )
    causal_model_path: Path = Field(
        default=BUNDLED_CAUSAL, description="causal temporal model (streams, `temporal: causal`)"
    )
    offline_model_path: Path = Field(
        default=BUNDLED_OFFLINE, description="offline temporal model (`temporal: offline`)"
    )
    max_temporal_poses: int = Field(
        default=Limits.max_temporal_poses,
        ge=1,
        description="most poses in one request with `temporal` causal or offline (and at most `queue_size`)",
    )
    stream_max_tracks: int = Field(default=64, ge=1, description="most open tracks of one `LiftStream`")
    max_tracks: int = Field(default=4096, ge=1, description="most open tracks of all streams together")
    track_memory_mb: int = Field(
        default=128,
        ge=1,
        description="most MiB of state the open tracks of all streams hold together (a track at F fps "
        "holds its window, about 0.65 x F KB: 20 KB at 30 fps, 157 KB at 240; the process's memory grows "
        "about 1.4 times that); a new track beyond it, or beyond `max_tracks`, is refused "
        "(`too_many_tracks`, `RESOURCE_EXHAUSTED`)",
    )
    track_idle_s: float = Field(
        default=10.0, gt=0, description="a stream's track that gets no frame for this long is dropped"
    )
    shutdown_grace_s: float = Field(
        default=10.0, ge=0, description="time to drain in-flight work after SIGTERM"
    )
    shutdown_delay_s: float = Field(
        default=0.0,
        ge=0,
        description="time between reporting not ready and refusing new requests (lets load balancers notice)",
    )
    ui: bool = Field(default=True, description="serve the web page at `GET /` (false: the API alone)")
    log_level: Literal["debug", "info", "warning", "error"] = Field(
        default="info", description="debug, info, warning or error"
    )

    @model_validator(mode="after")
    def _check_tls(self) -> Settings:
        if (self.tls_cert is None) != (self.tls_key is None):
            raise ValueError("tls_cert and tls_key go together: give both or neither")
        if self.tls_client_ca is not None and self.tls_cert is None:
            raise ValueError("tls_client_ca (mutual TLS) needs tls_cert and tls_key")
        return self

    @model_validator(mode="after")
    def _check_queue(self) -> Settings:
        if self.queue_size < self.max_request_poses:
            raise ValueError(
                f"queue_size ({self.queue_size}) must be at least max_request_poses "
                f"({self.max_request_poses}), or the largest request could never be queued"
            )
        return self


LOOPBACK_NAMES = ("localhost", "127.0.0.1", "[::1]")  # what a browser on this machine sends as Host


def trusted_hosts(settings: Settings) -> list[str] | None:
    """The Host names the HTTP server answers (settings.allowed_hosts; its default: LOOPBACK_NAMES for
    a loopback bind); None: any."""
    given = [h.strip() for h in (settings.allowed_hosts or "").split(",") if h.strip()]
    if given:
        return None if "*" in given else given
    try:
        loopback = ipaddress.ip_address(settings.host).is_loopback
    except ValueError:  # a name, not an address
        loopback = settings.host == "localhost"
    return list(LOOPBACK_NAMES) if loopback else None


def settings_table() -> str:
    """The Markdown table of every setting, its variable, default and meaning (docs/API.md holds it:
    `python -m repnet.server.config` prints it, and a test checks that the two agree)."""
    shown = {
        BUNDLED_MODEL: "bundled model",
        BUNDLED_CAUSAL: "bundled causal",
        BUNDLED_OFFLINE: "bundled offline",
    }
    lines = ["| variable | flag | default | meaning |", "| --- | --- | --- | --- |"]
    for name, field in Settings.model_fields.items():
        default = field.default
        if isinstance(default, Path) and default in shown:
            text = shown[default]
        elif default is None:
            text = "unset"
        elif isinstance(default, bool):
            text = str(default).lower()
        else:
            text = str(default)
        flag = "--" + name.replace("_", "-")
        lines.append(f"| `REPNET_{name.upper()}` | `{flag}` | `{text}` | {field.description} |")
    return "\n".join(lines)


if __name__ == "__main__":
    print(settings_table())
