"""One pass over a batch of jobs: the input rules, the single-frame model, the streams' tracks and the
causal temporal model, the replies, and each job's own answer (its `finish`), all over arrays of the
batch's poses. A job is a group of poses lifted and answered together: a stream's frames, a
request's poses. The batcher (runtime.batchers.LiftBatcher) runs it on its thread, one hand-off
between the event loop and that thread per job."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from repnet.core import geometry
from repnet.core.errors import LiftError, Violation
from repnet.core.inputs import Limits, ModelInput, PoseInput, Prepared
from repnet.core.keypoints import prepare_poses
from repnet.runtime.lifter import Lifter, Prediction
from repnet.runtime.plans import TrackedRow, answer_rows, stream_plan
from repnet.runtime.replies import Replies, TemporalRows, build_replies
from repnet.runtime.temporal import TemporalLifter
from repnet.runtime.tracks import TrackTable


@dataclass(frozen=True)
class TrackedPose:
    """What a tracked pose of a stream's frame says of its track."""

    track_id: str
    frame: int  # its frame number
    fps: float
    field: str  # what its errors are named: "pose", "people[2].pose"


@dataclass(frozen=True)
class StreamTracks:
    """A stream's tracks and the causal model that answers them (used on the batcher's thread only,
    one job of the stream at a time: server.stream takes a stream's next frames once its last job is
    answered)."""

    table: TrackTable
    temporal: TemporalLifter


@dataclass(frozen=True)
class Lifted:
    """What a job got: its poses after the input rules, the model's answers to the valid ones and
    their replies (None when the job asked for the prediction alone), and per valid row why its
    track refused it."""

    prepared: Prepared
    prediction: Prediction
    replies: Replies | None
    errors: dict[int, LiftError]


@dataclass
class Job:
    """Poses lifted together, answered together by `finish` (called on the batcher's thread with
    what the job got; what it returns is the job's answer, e.g. its encoded replies).

    poses -- the poses as received (the input rules run in the batch); or, instead, inputs already
      prepared (a temporal request's, whose rules ran on the loop);
    threshold -- the request's confidence threshold for the poses without their own (None: default);
    tracks, tracked -- the stream's tracks, and per pose its track (None: lifted alone);
    replies -- build the replies (False: the prediction alone)."""

    finish: Callable[[Lifted], Any]
    poses: Sequence[PoseInput] = ()
    inputs: ModelInput | None = None
    threshold: float | None = None
    tracks: StreamTracks | None = None
    tracked: Sequence[TrackedPose | None] = ()
    replies: bool = True
    track_ids: Sequence[str | None] | None = field(default=None)  # per pose, echoed in the replies

    def __len__(self) -> int:
        return len(self.inputs) if self.inputs is not None else len(self.poses)

    def slice(self, start: int, stop: int) -> Job:
        """The job itself: a batcher never slices a job (its poses are answered together; one that
        costs more than a run is split into jobs of its own before it is queued: split_job)."""
        if (start, stop) != (0, len(self)):
            raise ValueError("a job is lifted whole")
        return self


@dataclass(frozen=True)
class Parts:
    """A large job's poses in parts of at most a run's cost, each queued and answered apart (its
    Lifted), so that other clients' requests ride along with the next run instead of waiting for all
    of this job's runs; `job`'s finish answers their join (join_lifted)."""

    job: Job
    parts: list[Job]

    def __len__(self) -> int:
        return len(self.job)


def split_job(job: Job, max_cost: float) -> Parts | None:
    """`job` in consecutive parts of at most `max_cost` (job_cost; a pose that costs more is a part
    of its own), or None when it is lifted whole: a job of at most `max_cost`, or of prepared
    inputs. A stream's job keeps its tracks in every part: the parts run in order (one source's
    chunks leave the queue in order), so each track gets its poses in order, as in one pass."""
    # Most jobs (a camera's frame, a small request) fit whatever they hold: no cost summed for them.
    if job.inputs is not None or len(job.poses) * TRACKED_COST <= max_cost or job_cost(job) <= max_cost:
        return None
    tracked = job.tracks is not None
    bounds, cost, start = [], 0.0, 0
    for i in range(len(job.poses)):
        pose = TRACKED_COST if tracked and job.tracked[i] is not None else 1.0
        if i > start and cost + pose > max_cost:
            bounds.append((start, i))
            start, cost = i, 0.0
        cost += pose
    bounds.append((start, len(job.poses)))
    if len(bounds) == 1:  # one pose that costs more than a run: lifted whole
        return None
    parts = [
        Job(
            lifted_only,
            job.poses[a:b],
            threshold=job.threshold,
            tracks=job.tracks,
            tracked=job.tracked[a:b] if tracked else (),
            replies=job.replies,
            track_ids=None if job.track_ids is None else job.track_ids[a:b],
        )
        for a, b in bounds
    ]
    return Parts(job, parts)


def lifted_only(lifted: Lifted) -> Lifted:
    """A part's answer: what it got (joined for the whole job's finish)."""
    return lifted


def join_lifted(parts: Sequence[Lifted]) -> Lifted:
    """What the consecutive parts of a job got, as the whole job would have got it: violations and
    errors renumbered within the whole job."""
    if len(parts) == 1:
        return parts[0]
    violations: list[tuple[Violation, ...]] = []
    errors: dict[int, LiftError] = {}
    row = 0  # the part's first valid row in the job
    for part in parts:
        start = len(violations)
        violations += [
            tuple(v if v.pose is None else replace(v, pose=v.pose + start) for v in found)
            for found in part.prepared.violations
        ]
        errors.update((row + k, err) for k, err in part.errors.items())
        row += len(part.prepared.inputs)
    replies = [p.replies for p in parts]
    return Lifted(
        Prepared(join_inputs([p.prepared.inputs for p in parts]), tuple(violations)),
        Prediction.join([p.prediction for p in parts]),
        None if any(r is None for r in replies) else Replies.join([r for r in replies if r is not None]),
        errors,
    )


def prepare_jobs(jobs: Sequence[Job], limits: Limits) -> list[Prepared]:
    """Each job's poses after the input rules, in one pass over every job's poses (violations named
    by the pose's index in its own job)."""
    raw = [j for j in jobs if j.inputs is None]
    found: dict[int, Prepared] = {id(j): Prepared(j.inputs, ()) for j in jobs if j.inputs is not None}
    if raw:
        poses = [with_threshold(p, j.threshold) for j in raw for p in j.poses]
        whole = prepare_poses(poses, limits)
        start, row = 0, 0
        for job in raw:
            stop = start + len(job.poses)
            violations = whole.violations[start:stop]
            valid = sum(1 for v in violations if not v)
            renumbered = tuple(tuple(replace(v, pose=(v.pose or 0) - start) for v in f) for f in violations)
            found[id(job)] = Prepared(whole.inputs.slice(row, row + valid), renumbered)
            start, row = stop, row + valid
    return [found[id(j)] for j in jobs]


def with_threshold(pose: PoseInput, threshold: float | None) -> PoseInput:
    """The pose with the request's threshold where it has none of its own."""
    if threshold is None or pose.confidence_threshold is not None:
        return pose
    return replace(pose, confidence_threshold=threshold)


def join_inputs(parts: Sequence[ModelInput]) -> ModelInput:
    """Consecutive ModelInputs as one."""
    if len(parts) == 1:
        return parts[0]
    names = ModelInput.__dataclass_fields__
    return ModelInput(**{n: np.concatenate([getattr(p, n) for p in parts]) for n in names})


def lift_all(lifter: Lifter, inputs: ModelInput, max_batch: int) -> Prediction:
    """The model's answers to every row, max_batch rows per run."""
    n = len(inputs)
    if n == 0:  # every pose of the batch broke a rule: nothing to run
        plausibility = np.zeros(0, np.float32) if lifter.has_plausibility else None
        joints = inputs.keypoints_2d.shape[1]
        pose, camera = np.zeros((0, joints, 3), np.float32), np.zeros((0, 2, 3), np.float32)
        return Prediction(pose, camera, np.zeros(0, bool), plausibility)
    if n <= max_batch:
        return lifter.run([inputs])
    return Prediction.join(
        [lifter.run([inputs.slice(a, min(a + max_batch, n))]) for a in range(0, n, max_batch)]
    )


def track_rows(job: Job, prepared: Prepared, offset: int) -> list[TrackedRow]:
    """The job's valid tracked poses, each with its row in the batch (its row among the job's valid
    poses plus `offset`, the job's first)."""
    rows: list[TrackedRow] = []
    row = offset
    for found, spec in zip(prepared.violations, job.tracked, strict=True):
        if found:
            continue
        if spec is not None:
            rows.append(TrackedRow(row, spec.track_id, spec.frame, spec.fps, spec.field))
        row += 1
    return rows


def temporal_rows(
    jobs: Sequence[Job],
    prepared: Sequence[Prepared],
    inputs: ModelInput,
    prediction: Prediction,
    offsets: Sequence[int],
    rotation: np.ndarray,
) -> tuple[TemporalRows, list[dict[int, LiftError]]]:
    """The streams' tracked poses pushed into their tracks and answered by their causal model, all
    jobs' poses together, one plan and one run per model: TemporalRows in the batch's rows, and per
    job why a row (of its own) has none."""
    errors: list[dict[int, LiftError]] = [{} for _ in jobs]
    tracked: dict[int, tuple[TemporalLifter, list[tuple[TrackTable, TrackedRow]]]] = {}  # by id(model)
    owner: dict[int, int] = {}  # a tracked row -> its job
    for k, (job, ready) in enumerate(zip(jobs, prepared, strict=True)):
        if job.tracks is None or not job.tracked:
            continue
        mine = track_rows(job, ready, offsets[k])
        if not mine:
            continue
        owner.update((t.row, k) for t in mine)
        model = job.tracks.temporal
        tracked.setdefault(id(model), (model, []))[1].extend((job.tracks.table, t) for t in mine)
    found = [TemporalRows.none()]
    for model, poses in tracked.values():
        plan = stream_plan(poses, inputs, prediction, rotation)
        for row, err in plan.errors.items():
            errors[owner[row]][row - offsets[owner[row]]] = err
        if plan.windows is not None:
            found.append(answer_rows(plan, model.run(plan.windows.build())))
    return join_rows(found), errors


def join_rows(parts: Sequence[TemporalRows]) -> TemporalRows:
    """TemporalRows of disjoint rows as one."""
    parts = [p for p in parts if len(p.rows)] or [TemporalRows.none()]
    if len(parts) == 1:
        return parts[0]
    return TemporalRows(
        np.concatenate([p.rows for p in parts]),
        np.concatenate([p.pose_camera for p in parts]),
        np.concatenate([p.failed for p in parts]),
    )


def valid_track_ids(jobs: Sequence[Job], prepared: Sequence[Prepared]) -> list[str | None]:
    """Per valid row of the batch, its pose's track id as the reply echoes it."""
    out: list[str | None] = []
    for job, ready in zip(jobs, prepared, strict=True):
        ids = job.track_ids
        if ids is None and job.tracked:
            ids = [None if t is None else t.track_id for t in job.tracked]
        if job.inputs is not None:
            out += list(ids) if ids is not None else [None] * len(ready.inputs)
            continue
        for found, track in zip(ready.violations, ids or [None] * len(job.poses), strict=True):
            if not found:
                out.append(track)
    return out


@dataclass(frozen=True)
class Batch:
    """What one pass answered: each job's answer in order, and the model's answers to every valid row."""

    answers: list[Any]
    prediction: Prediction
    rows: list[int]  # per job, its poses that passed the input rules (the rows lifted)


def run_jobs(lifter: Lifter, jobs: Sequence[Job], limits: Limits, max_batch: int) -> Batch:
    """One pass over a batch of jobs: each job's answer (its finish of what it got), in order."""
    prepared = prepare_jobs(jobs, limits)
    inputs = join_inputs([p.inputs for p in prepared])
    prediction = lift_all(lifter, inputs, max_batch)
    offsets = np.concatenate([[0], np.cumsum([len(p.inputs) for p in prepared])]).tolist()
    with np.errstate(over="ignore", invalid="ignore"):  # what is not finite fails its pose (replies)
        rotation = geometry.camera_rotation(prediction.camera)  # once for the tracks and the replies
    rows, errors = temporal_rows(jobs, prepared, inputs, prediction, offsets, rotation)
    replies = None
    if any(j.replies for j in jobs):
        replies = build_replies(inputs, prediction, rows, valid_track_ids(jobs, prepared), rotation)
    answers = []
    for k, (job, ready) in enumerate(zip(jobs, prepared, strict=True)):
        a, b = offsets[k], offsets[k + 1]
        mine = replies.slice(a, b) if replies is not None and job.replies else None
        try:
            answers.append(job.finish(Lifted(ready, prediction.slice(a, b), mine, errors[k])))
        except LiftError as err:  # the job's own refusal (InvalidKeypoints, ModelOutputError): its answer
            answers.append(err.as_answer())
        except Exception as err:  # a bug: kept with its traceback for the adapter's log
            answers.append(err)
    return Batch(answers, prediction, [len(p.inputs) for p in prepared])


# A tracked pose takes this many untracked poses' share of a run. Both models' per-pose roof against
# the single-frame model's alone is 1/6 at batch 64 (docs/BENCHMARKS.md), and a run holds at most
# max_batch of cost: 256 poses, or 32 tracked ones, a run of ~15 ms on one core, so that a request
# that comes during a run waits for that short run, not a long one (bench.fairness: a camera's p99
# under a flood of tracked crowds 216 ms with 64 tracked poses a run, 87-106 ms with 32; saturated
# tracked streams lose 6 %). REPNET_MAX_BATCH 512 gives 64 a run.
TRACKED_COST = 8.0


def job_cost(job: Job) -> float:
    """What a job takes of a run's capacity (max_batch): its poses, a tracked one TRACKED_COST."""
    tracked = sum(t is not None for t in job.tracked) if job.tracks is not None else 0
    return float(len(job)) + (TRACKED_COST - 1.0) * tracked


def prediction_only(inputs: ModelInput) -> Job:
    """A job that asks for the model's answers to prepared inputs, nothing more."""
    return Job(finish=lambda lifted: lifted.prediction, inputs=inputs, replies=False)
