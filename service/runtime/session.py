"""An onnxruntime session of a model file: its options (threads, spinning), the file read safely (a regular
file of bounded size, hashed in chunks), the graph outputs the service never reads cut at load and the
rewrites that keep its answers (runtime.rewrite)."""

from __future__ import annotations

import hashlib
import os
import stat
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO, Protocol

import onnxruntime as ort

from repnet.core.errors import ModelLoadError
from repnet.runtime.rewrite import broadcasts_widened, convs_as_matmuls

# onnxruntime >= 1.29 sends usage telemetry on Linux unless told not to: off before this package makes
# any session, whatever started it (repnet serve, repnet lift --local, repnet adapt, a script).
ort.disable_telemetry_events()


@dataclass(frozen=True)
class SessionOptions:
    """onnxruntime's options of a session; the defaults are the service's (Settings takes its own
    from here, and passes itself: it has these three fields)."""

    intra_op_threads: int = 0  # threads per run (0: one per core)
    inter_op_threads: int = 1
    intra_op_spinning: bool = False  # threads spin between runs


class HasSessionOptions(Protocol):
    """What open_session reads: SessionOptions, or the server's Settings."""

    @property
    def intra_op_threads(self) -> int:
        """Threads per run."""

    @property
    def inter_op_threads(self) -> int:
        """Inter-op threads."""

    @property
    def intra_op_spinning(self) -> bool:
        """Spin between runs."""


# Graph outputs the service never reads: a model's training critic (`repnet adapt` reads its weights
# from the file). They are cut from the graph at load, with every node only they need: the bundled
# model's critic is 144 of its 243 nodes and 40 % of a batch-1 run.
UNREAD_OUTPUTS = ("critic",)


MAX_MODEL_BYTES = 512 * 1024 * 1024  # a model file larger than this is refused at load


def open_model_file(path: Path) -> BinaryIO:
    """The model file at `path`, open for reading: a regular file (not a folder, FIFO or device; a
    link is followed) of at most MAX_MODEL_BYTES; ModelLoadError saying why not. Opened without
    blocking and checked open, so a FIFO cannot hang the start nor a file swapped after a check pass."""
    if path.is_dir():
        raise ModelLoadError(f"model path is a directory, not an ONNX file: {path}")
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    except OSError as err:
        if isinstance(err, FileNotFoundError):
            raise ModelLoadError(f"model file not found: {path}") from None
        raise ModelLoadError(f"cannot read model file {path}: {err.strerror}") from None
    info = os.fstat(fd)
    if not stat.S_ISREG(info.st_mode):
        os.close(fd)
        raise ModelLoadError(f"{path}: not a regular file (a model is an .onnx file)")
    if info.st_size > MAX_MODEL_BYTES:
        os.close(fd)
        raise ModelLoadError(f"{path}: {info.st_size} bytes, more than a model may have ({MAX_MODEL_BYTES})")
    return os.fdopen(fd, "rb")


def read_model(path: Path) -> bytes:
    """The bytes of the model file at `path` (open_model_file's checks)."""
    with open_model_file(path) as f:
        return f.read(MAX_MODEL_BYTES + 1)


def model_sha256(path: Path) -> str:
    """The sha256 of the model file at `path` (open_model_file's checks), read in chunks of 1 MiB."""
    digest = hashlib.sha256()
    with open_model_file(path) as f:
        while block := f.read(1 << 20):
            digest.update(block)
    return digest.hexdigest()


def _pruned(model: Any) -> Any:
    """onnx `model` without the UNREAD_OUTPUTS and the nodes only they need (metadata kept); the
    same object when it has none of them."""
    from onnx import utils

    names = [o.name for o in model.graph.output]
    kept = [n for n in names if n not in UNREAD_OUTPUTS]
    if kept == names:
        return model
    inputs = [i.name for i in model.graph.input if i.name not in {t.name for t in model.graph.initializer}]
    pruned = utils.Extractor(model).extract_model(inputs, kept)
    pruned.metadata_props.extend(model.metadata_props)
    pruned.doc_string = model.doc_string
    return pruned


def served_graph(data: bytes) -> bytes:
    """The graph the service runs of the model `data`: without the UNREAD_OUTPUTS, its strided 1D
    convolutions as matrix products and its broadcasts over short trailing axes tiled
    (runtime.rewrite: the same answers to float32 rounding); the same bytes when none applies."""
    import onnx  # the runtime's extras bring it; loaded only here

    model = onnx.load_from_string(data)
    pruned = _pruned(model)
    rewritten = convs_as_matmuls(pruned) + broadcasts_widened(pruned)
    if rewritten == 0 and pruned is model:
        return data
    return bytes(pruned.SerializeToString())


def open_session(path: Path, settings: HasSessionOptions | None = None) -> ort.InferenceSession:
    """An onnxruntime session of the model at `path` (read_model; UNREAD_OUTPUTS cut) with the
    options of `settings` (threads and spinning; default SessionOptions()); ModelLoadError saying why
    the file cannot be one."""
    settings = SessionOptions() if settings is None else settings
    data = read_model(path)
    options = ort.SessionOptions()
    options.intra_op_num_threads = settings.intra_op_threads  # 0: one per core
    options.inter_op_num_threads = settings.inter_op_threads
    spinning = "1" if settings.intra_op_spinning else "0"
    options.add_session_config_entry("session.intra_op.allow_spinning", spinning)
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    try:
        return ort.InferenceSession(served_graph(data), options, providers=["CPUExecutionProvider"])
    except Exception as err:  # onnxruntime and onnx raise their own untyped errors for bad files
        raise ModelLoadError(f"cannot load model {path}: {' '.join(str(err).split())[:500]}") from err
