"""Settings of the service: environment variables with the REPNET_ prefix, then flags."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

MODELS = Path(__file__).resolve().parent / "models"
BUNDLED_MODEL = MODELS / "repnet-h36m.onnx"
BUNDLED_CAUSAL = MODELS / "repnet-h36m-temporal-causal.onnx"
BUNDLED_OFFLINE = MODELS / "repnet-h36m-temporal-offline.onnx"


class Settings(BaseSettings):
    """Everything an operator can set, and the only place a default lives. app.main creates it once
    and passes it down (Lifter, Engine, Limits, the HTTP app and the gRPC server take no defaults)."""

    model_config = SettingsConfigDict(env_prefix="REPNET_", extra="ignore", frozen=True)

    model_path: Path = Field(
        default=BUNDLED_MODEL, description="ONNX model file (the bundled model by default)"
    )
    host: str = Field(default="0.0.0.0", description="address both servers bind to")
    http_port: int = Field(default=8000, ge=0, le=65535, description="HTTP port (0: any free port)")
    grpc_port: int = Field(default=50051, ge=0, le=65535, description="gRPC port (0: any free port)")
    intra_op_threads: int = Field(
        default=0, ge=0, description="onnxruntime threads per run (0: one per core)"
    )
    inter_op_threads: int = Field(default=1, ge=0, description="onnxruntime inter-op threads")
    intra_op_spinning: bool = Field(
        default=False,
        description="onnxruntime threads spin between runs (faster single runs on idle cores; off "
        "leaves the CPU to the server's own threads, +20 % stream throughput on 2 cores: docs/BENCHMARKS.md)",
    )
    grpc_workers: int = Field(
        default=32,
        ge=1,
        description="most gRPC Lift calls in progress at once; beyond: RESOURCE_EXHAUSTED (streams "
        "have their own limit, health checks none)",
    )
    grpc_max_streams: int = Field(
        default=64, ge=1, description="most LiftStream calls open at once; beyond: RESOURCE_EXHAUSTED"
    )
    stream_idle_timeout_s: float = Field(
        default=60.0,
        gt=0,
        description="a LiftStream with nothing in progress that sends no frame for this long is "
        "closed with DEADLINE_EXCEEDED",
    )
    http_max_in_flight: int = Field(
        default=128,
        ge=1,
        description="most POST /lift requests in progress at once; beyond: 503 with Retry-After at "
        "once, before the body is read (health, readiness and metrics are never refused)",
    )
    max_batch: int = Field(default=256, ge=1, description="most poses in one onnxruntime run")
    max_wait_ms: float = Field(
        default=0.5,
        ge=0,
        description="under load, longest the batcher waits for more poses to join a batch (an idle "
        "batcher runs a request at once)",
    )
    queue_size: int = Field(default=8192, ge=1, description="most poses waiting for a run; beyond: 503")
    max_request_poses: int = Field(default=1024, ge=1, description="most poses in one request")
    max_body_bytes: int = Field(
        default=4 * 1024 * 1024, ge=1024, description="largest HTTP body / gRPC message"
    )
    min_visible_joints: int = Field(
        default=6, ge=2, le=17, description="fewest visible model joints per pose"
    )
    confidence_threshold: float = Field(
        default=0.2, ge=0, le=1, description="default: a joint with confidence below it counts as missing"
    )
    max_coordinate: float = Field(default=1e6, gt=0, description="largest accepted |x| or |y| in pixels")
    stream_window: int = Field(default=256, ge=1, description="frames of one stream in flight at once")
    temporal: bool = Field(
        default=True,
        description="load the temporal models (tracked poses of streams and of temporal requests); false: "
        "every pose is lifted alone",
    )
    causal_model_path: Path = Field(
        default=BUNDLED_CAUSAL, description="causal temporal model (streams, temporal: causal)"
    )
    offline_model_path: Path = Field(default=BUNDLED_OFFLINE, description="offline temporal model")
    max_temporal_poses: int = Field(
        default=6000,
        ge=1,
        description="most poses in one request with temporal causal or offline (and at most queue_size)",
    )
    stream_max_tracks: int = Field(default=64, ge=1, description="most open tracks of one LiftStream")
    max_tracks: int = Field(default=4096, ge=1, description="most open tracks of all streams together")
    track_idle_s: float = Field(
        default=10.0, gt=0, description="a stream's track that gets no frame for this long is dropped"
    )
    shutdown_grace_s: float = Field(
        default=10.0, ge=0, description="time to drain in-flight work at shutdown"
    )
    shutdown_delay_s: float = Field(
        default=0.0, ge=0, description="time between reporting not ready and refusing new requests"
    )
    ui: bool = Field(default=True, description="serve the web page at GET / (false: the API alone)")
    log_level: Literal["debug", "info", "warning", "error"] = "info"

    @model_validator(mode="after")
    def _check_queue(self) -> Settings:
        if self.queue_size < self.max_request_poses:
            raise ValueError(
                f"queue_size ({self.queue_size}) must be at least max_request_poses "
                f"({self.max_request_poses}), or the largest request could never be queued"
            )
        return self
