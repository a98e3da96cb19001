"""`repnet lift --local`: the core the servers use, in this process (load checks, input rules, the
single-frame and temporal models, the reply), cut into requests as the HTTP client cuts them."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from repnet.cli.usable import pose_inputs
from repnet.client.body import Batch
from repnet.client.chunks import Part, Progress, batches, lift_parts, split_clip
from repnet.client.result import LiftClientError, LiftResult
from repnet.core.errors import InvalidKeypoints, LiftError
from repnet.core.inputs import Limits, ModelInput
from repnet.core.keypoints import prepare_request
from repnet.runtime.batcher import MAX_BATCH
from repnet.runtime.lifter import Lifter, Prediction
from repnet.runtime.loading import (
    BUNDLED_CAUSAL,
    BUNDLED_MODEL,
    BUNDLED_OFFLINE,
    check_lifter,
    load_temporal_lifters,
)
from repnet.runtime.plans import answer_rows, clip_plan, clip_violations
from repnet.runtime.replies import TemporalRows, build_replies
from repnet.runtime.temporal import TemporalAnswer, TemporalLifter

TEMPORAL_MODELS = {"causal": BUNDLED_CAUSAL, "offline": BUNDLED_OFFLINE}  # mode -> path


class LocalBackend:
    """The bundled models (or `model`, with the bundled temporal models where they were trained on
    it) in this process, with the service's default limits: single-frame requests of `batch` poses,
    temporal ones of Limits.max_temporal_poses."""

    def __init__(self, model: Path | None, batch: int) -> None:
        path = BUNDLED_MODEL if model is None else model
        self.lifter = check_lifter(Lifter.load(path))
        self.temporal: dict[str, TemporalLifter] = load_temporal_lifters(path, self.lifter, TEMPORAL_MODELS)
        self._limits = Limits(max_request_poses=batch)
        self.batch = batch
        self.max_temporal_poses = Limits.max_temporal_poses
        self.max_batch = MAX_BATCH  # windows per temporal model run

    def limits(self) -> Limits:
        """The service's default limits."""
        return self._limits

    def temporal_modes(self) -> tuple[str, ...]:
        """The temporal modes of the loaded models."""
        return tuple(sorted(self.temporal))

    def lift_batch(self, batch: Batch, progress: Progress | None = None) -> list[LiftResult]:
        """Lift a batch as LiftClient.lift_batch does, through the same parts (repnet.client.chunks);
        LiftClientError ("rejected") naming the pose of the batch."""
        count, tracking = len(batch.points), batch.tracking
        if tracking.temporal == "off" or not count:
            parts = batches(count, self.batch)
        else:
            temporal = self.temporal.get(tracking.temporal)
            if temporal is None:
                reason = f"no {tracking.temporal} temporal model is loaded (REPNET_TEMPORAL, its model path)"
                raise LiftClientError(reason, "rejected")
            reach = temporal.contract.reach(float(tracking.fps or 0.0))
            frames = tracking.frames if tracking.frames is not None else np.zeros(count, np.int64)
            try:
                parts = split_clip(
                    tracking.track_ids or (None,) * count, frames, reach, self.max_temporal_poses
                )
            except ValueError as err:
                raise LiftClientError(str(err), "rejected") from err

        def lift(part: Part) -> list[LiftResult]:
            try:
                return self._lift(batch, part.send)
            except LiftError as err:
                raise LiftClientError(str(err), "rejected").renumbered(part.send.tolist()) from err

        return lift_parts(count, parts, lift, progress)

    def _lift(self, batch: Batch, send: np.ndarray) -> list[LiftResult]:
        """One request of the poses at `send`, answered as the HTTP adapter answers it."""
        points, conf, tracking = batch.points, batch.conf, batch.tracking
        poses = pose_inputs(
            points, conf, batch.format, send.tolist(), batch.intrinsics, batch.person_height_m
        )
        ids = None if tracking.track_ids is None else [tracking.track_ids[i] for i in send.tolist()]
        frames = None if tracking.frames is None else tracking.frames[send]
        temporal = self.temporal.get(tracking.temporal)
        limits = self._limits
        if temporal is not None and ids is not None and frames is not None:
            limits = replace(limits, max_request_poses=self.max_temporal_poses)
            if found := clip_violations(ids, frames.tolist(), tracking.fps):
                raise InvalidKeypoints(found)
        inputs = prepare_request(len(poses), poses.__getitem__, batch.threshold, limits)
        prediction = self.lifter.lift(inputs.keypoints_2d, inputs.visible)
        rows = None
        if temporal is not None and ids is not None and frames is not None:
            rows = self._temporal(temporal, inputs, prediction, ids, frames, tracking.fps or 0.0)
        replies = build_replies(inputs, prediction, rows, ids).check()
        info = self.lifter.info
        return [
            LiftResult.from_fields(d.__getitem__, info.joint_names, info.model_id) for d in replies.to_json()
        ]

    def _temporal(
        self,
        temporal: TemporalLifter,
        inputs: ModelInput,
        prediction: Prediction,
        ids: Sequence[str | None],
        frames: np.ndarray,
        fps: float,
    ) -> TemporalRows:
        """The temporal answers of the tracked poses of one request (repnet.runtime.plans, as
        http_temporal plans them), the model run max_batch windows at a time."""
        tracked = [k for k, t in enumerate(ids) if t is not None]
        rows = np.array(tracked, np.int64)
        plan = clip_plan(
            rows, [str(ids[k]) for k in tracked], frames[rows], fps, temporal.contract, inputs, prediction
        )
        if plan.windows is None:
            return TemporalRows.none()
        n = len(plan.windows)
        answers = [
            temporal.run(plan.windows.slice(a, a + self.max_batch).build())
            for a in range(0, n, self.max_batch)
        ]
        return answer_rows(plan, TemporalAnswer.join(answers))
