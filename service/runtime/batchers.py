"""The batchers of the two kinds of model: LiftBatcher runs a single-frame Lifter (ModelInput ->
Prediction), TemporalBatcher a TemporalLifter (windows -> TemporalAnswer)."""

from __future__ import annotations

from repnet.core.inputs import ModelInput
from repnet.runtime.batcher import Batcher, BatchMetrics
from repnet.runtime.lifter import Lifter, Prediction
from repnet.runtime.temporal import TemporalAnswer, TemporalLifter, Windows, WindowSource


class LiftBatcher(Batcher[ModelInput, Prediction]):
    """A single-frame model's batcher: ModelInputs in, Predictions out; its metrics are labelled
    with the model's id (its runs hold only that model's poses)."""

    def __init__(
        self,
        lifter: Lifter,
        metrics: BatchMetrics | None,
        *,
        max_batch: int,
        max_wait_s: float,
        queue_size: int,
    ) -> None:
        self.lifter = lifter
        model = lifter.info.model_id
        super().__init__(
            metrics, max_batch=max_batch, max_wait_s=max_wait_s, queue_size=queue_size, name=model
        )

    def _run(self, parts: list[ModelInput]) -> Prediction:
        return self.lifter.run(parts)

    def _join(self, parts: list[Prediction]) -> Prediction:
        return Prediction.join(parts)

    def _observe(self, answer: Prediction) -> None:
        if self.metrics is not None and answer.plausibility is not None and not answer.failed.any():
            self.metrics.observe_plausibility(self.model, answer.plausibility)


class TemporalBatcher(Batcher[WindowSource, TemporalAnswer]):
    """A temporal model's batcher: windows in (of any length: padded; ClipWindows built batch by
    batch on its thread, so a request's windows are never all built at once), TemporalAnswers out.
    Its runs are not in the single-frame metrics (inference_seconds, batch size)."""

    def __init__(self, lifter: TemporalLifter, *, max_batch: int, max_wait_s: float, queue_size: int) -> None:
        self.lifter = lifter
        super().__init__(
            None,
            max_batch=max_batch,
            max_wait_s=max_wait_s,
            queue_size=queue_size,
            name=f"{lifter.mode}-batcher",
        )

    def _run(self, parts: list[WindowSource]) -> TemporalAnswer:
        built = [p.build() for p in parts]
        return self.lifter.run(Windows.join(built, causal=self.lifter.mode == "causal"))

    def _join(self, parts: list[TemporalAnswer]) -> TemporalAnswer:
        return TemporalAnswer.join(parts)
