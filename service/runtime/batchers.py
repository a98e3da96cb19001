"""The single-frame model's batcher, LiftBatcher: a Lifter's jobs (runtime.pipeline: poses in, each
job's answer out). A temporal model's is runtime.temporal.TemporalBatcher."""

from __future__ import annotations

from collections.abc import Hashable
from concurrent.futures import Future
from typing import Any

from repnet.core.inputs import Limits, ModelInput
from repnet.runtime.batcher import Batcher, BatchMetrics, offload
from repnet.runtime.fair_queue import Chunk
from repnet.runtime.lifter import Lifter, Prediction
from repnet.runtime.pipeline import (
    Batch,
    Job,
    Lifted,
    Parts,
    job_cost,
    join_lifted,
    prediction_only,
    run_jobs,
    split_job,
)


class LiftBatcher(Batcher[Any, Any]):
    """A single-frame model's batcher: jobs in (runtime.pipeline), each answered whole by one pass
    over its batch on this batcher's thread (the input rules, the model, a stream's tracks and
    causal model, the replies, the job's own encoding); a job that costs more than a run (max_batch)
    is queued in parts of at most a run's cost, each answered apart (split_job); a ModelInput submitted
    alone is answered with its Prediction, max_batch rows a chunk, each chunk a job of its own. Its
    metrics are labelled with the model's id (its runs hold only that model's poses)."""

    def __init__(
        self,
        lifter: Lifter,
        metrics: BatchMetrics | None,
        *,
        max_batch: int,
        max_wait_s: float,
        queue_size: int,
        limits: Limits | None = None,
        company_wait_s: float = 0.0,
    ) -> None:
        self.lifter = lifter
        self.limits = Limits() if limits is None else limits
        model = lifter.info.model_id
        super().__init__(
            metrics,
            max_batch=max_batch,
            max_wait_s=max_wait_s,
            queue_size=queue_size,
            name=model,
            company_wait_s=company_wait_s,
        )

    def _chunks(
        self, inputs: Job | Parts | ModelInput, transport: str, source: Hashable
    ) -> list[Chunk[Job, Any]]:
        if isinstance(inputs, (Job, Parts)):  # a job lifted whole, or each part of one queued apart
            jobs = inputs.parts if isinstance(inputs, Parts) else [inputs]
            return [Chunk(j, transport, 0.0, Future(), source, job_cost(j)) for j in jobs]
        # Prepared inputs (a temporal request's poses): the batcher's chunks of max_batch rows, queued
        # apart, so that another client's request waits for one run, not for all of a 6,000-pose
        # request's runs in one pass (about 0.5 s); no rows, one empty chunk (answered empty).
        return super()._chunks(inputs, transport, source) or [
            Chunk(inputs, transport, 0.0, Future(), source, 0.0)
        ]

    def _run(self, parts: list[Job | ModelInput]) -> Batch:
        jobs = [part if isinstance(part, Job) else prediction_only(part) for part in parts]
        return run_jobs(self.lifter, jobs, self.limits, self.max_batch)

    def _results(self, answer: Batch, batch: list[Chunk[Job, Any]]) -> list[Any]:
        return answer.answers

    def _lifted(self, answer: Batch, batch: list[Chunk[Job, Any]]) -> list[int]:
        return answer.rows  # a job's poses that passed the input rules

    def _join(self, parts: list[Any]) -> Any:
        if len(parts) == 1:
            return parts[0]
        return join_lifted(parts) if isinstance(parts[0], Lifted) else Prediction.join(parts)

    def _observe(self, answer: Batch) -> None:
        found = answer.prediction
        if self.metrics is not None and found.plausibility is not None and not found.failed.any():
            self.metrics.observe_plausibility(self.model, found.plausibility)

    async def queue_async(
        self, job: Job, transport: str, wait_s: float = 0.0, source: Hashable = None
    ) -> list[Future[Any]]:
        """Queue `job` for `source`, in parts when split_job splits it (Overloaded when the queue
        stays full for wait_s), without waiting for its runs; answer() gives its answer once every
        future is done (a stream's frames: server.stream)."""
        return await self.submit_async(split_job(job, self.max_batch) or job, transport, wait_s, source)

    async def answer(self, job: Job, futures: list[Future[Any]]) -> Any:
        """The answer of `job` queued by queue_async, once every future is done: its finish's on
        the batcher's thread, or, for a job queued in parts, its finish of their join (off the
        event loop; split_job makes two parts or more). A failed run raises its error."""
        if len(futures) == 1:
            return futures[0].result()
        return await offload(len(job), job.finish, self._join([f.result() for f in futures]))

    async def run_async(self, job: Job, transport: str, wait_s: float = 0.0, source: Hashable = None) -> Any:
        """Queue `job` for `source` (Overloaded when the queue stays full for wait_s) and await its
        answer. A job that costs more than a run is queued in parts (split_job), and its finish runs
        on their join, off the event loop; when the caller is cancelled, its parts still queued are
        dropped (lift_async)."""
        parts = split_job(job, self.max_batch)
        if parts is None:
            return await self.lift_async(job, transport, wait_s, source)
        lifted = await self.lift_async(parts, transport, wait_s, source)
        return await offload(len(job), job.finish, lifted)

    def run(self, job: Job, transport: str) -> Any:
        """Queue `job`, wait for its batches and return its answer (run_async for threads)."""
        parts = split_job(job, self.max_batch)
        if parts is None:
            return super().lift(job, transport)
        return job.finish(super().lift(parts, transport))

    async def predict_async(
        self, inputs: ModelInput, transport: str, wait_s: float = 0.0, source: Hashable = None
    ) -> Prediction:
        """The model's answers to prepared inputs (queued max_batch rows a chunk, other requests
        riding along between them)."""
        found: Prediction = await self.lift_async(inputs, transport, wait_s, source)
        return found

    def predict(self, inputs: ModelInput, transport: str) -> Prediction:
        """predict_async for threads."""
        found: Prediction = super().lift(inputs, transport)
        return found
