"""Catalog: the single-frame models one service serves, each behind its own LiftBatcher, the default,
and the rule that picks one for a request (a field-level error naming the known ones)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

from repnet.core.errors import InvalidKeypoints, Violation, clip
from repnet.runtime.batchers import LiftBatcher

MODEL_FIELD = "model"  # the request field that names a model, on every transport


@dataclass(frozen=True)
class Catalog:
    """Engines by model id, the default first. Each model has its own batcher, so a batch never
    holds two models' poses, and its own queue of at most queue_size poses: a flood on one model
    fills that model's queue (503 / RESOURCE_EXHAUSTED for it) while the others keep theirs.

    `temporal_models`: the models temporal lifting runs over (empty without temporal models): the
    one the temporal models were loaded with, and those adapted from the model they were trained on
    (runtime.loading.serves_under). A request for temporal lifting with any other model gets a
    field-level error.
    """

    engines: dict[str, LiftBatcher]
    temporal_models: frozenset[str] = frozenset()
    sha256: dict[str, str] = field(default_factory=dict)  # each model file's, by id (lineage)
    # Whether the service's other workers serve too (server.workers; None: one process).
    peers_ready: Callable[[], bool] | None = None

    def runs_temporal(self, model: str) -> bool:
        """Whether temporal lifting runs over model `model`."""
        return model in self.temporal_models

    def __post_init__(self) -> None:
        if not self.engines:
            raise ValueError("a catalog holds at least one model")

    @classmethod
    def of(cls, engine: LiftBatcher | Catalog, temporal: bool = False) -> Catalog:
        """`engine` as a catalog of its one model (a catalog as it is); `temporal`: the temporal
        models run over it."""
        if isinstance(engine, Catalog):
            return engine
        model = engine.lifter.info.model_id
        return cls({model: engine}, frozenset({model} if temporal else ()))

    @property
    def default(self) -> str:
        """The id of the model a request that names none gets."""
        return next(iter(self.engines))

    @property
    def default_engine(self) -> LiftBatcher:
        """The default model's batcher."""
        return self.engines[self.default]

    def known(self) -> str:
        """The model ids, for error messages: 'a (default), b'."""
        return ", ".join(f"{m} (default)" if m == self.default else m for m in self.engines)

    def violation(self, name: str | None, temporal: bool = False) -> Violation | None:
        """Why `name` cannot serve a request (None: it can); empty or None names the default.
        `temporal`: the request asks for temporal lifting, which runs over temporal_models only."""
        model = name or self.default
        if model not in self.engines:
            reason = f"unknown model {clip(model, 100)!r}; this service serves: {self.known()}"
            return Violation(MODEL_FIELD, reason, "unknown_model")
        if temporal and self.temporal_models and not self.runs_temporal(model):
            over = ", ".join(repr(m) for m in self.engines if self.runs_temporal(m))
            reason = (
                f"temporal lifting runs over {over} (the model its temporal models were trained on, "
                f"and those adapted from it), not {model!r}: name one of them (or none), or lift "
                "without temporal"
            )
            return Violation(MODEL_FIELD, reason, "model_not_temporal")
        return None

    def pick(self, name: str | None, temporal: bool = False) -> LiftBatcher:
        """The engine of model `name` (empty or None: the default); InvalidKeypoints naming the
        known models when there is none of that name (see violation)."""
        if (found := self.violation(name, temporal)) is not None:
            raise InvalidKeypoints([found])
        return self.engines[name or self.default]

    @property
    def ready(self) -> bool:
        """Every model is loaded, the server is not shutting down, and every worker serves."""
        mine = all(e.ready for e in self.engines.values())
        return mine and (self.peers_ready is None or self.peers_ready())

    def stop_serving(self) -> None:
        """Report not ready from now on (every engine)."""
        for engine in self.engines.values():
            engine.stop_serving()

    def close(self, timeout: float | None = None) -> bool:
        """Close every engine (each finishes its queue); False if any timed out."""
        return all([engine.close(timeout) for engine in self.engines.values()])
