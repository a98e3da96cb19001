"""A stream's frames: what one frame holds (a pose, or several tracked people), how frames are
grouped to be lifted together, and each frame's answer (no wire format, no event loop)."""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Any

from repnet.core.errors import InvalidKeypoints, LiftError, ModelOutputError
from repnet.core.inputs import PoseInput, Prepared
from repnet.runtime.pipeline import TrackedPose
from repnet.runtime.replies import Replies, TemporalRows

POSE_FIELD = "pose"  # what a single pose's violations are named within: pose.keypoints[4]


@dataclass(frozen=True)
class PersonIn:
    """One person of a frame with several: a pose to lift (tracked), or why it has none."""

    track_id: str
    field: str  # what its violations are named within, e.g. "people[2]"
    pose: PoseInput | None = None
    error: LiftError | None = None


@dataclass(frozen=True)
class FrameIn:
    """One frame as the adapter read it: a pose to lift (tracked when track_id is not empty), or
    several people (`people`, each tracked), or why it has none (`error`, for the whole frame)."""

    frame_id: int  # also the frame's number in time for its tracks
    read_at: float  # time.perf_counter() when read
    pose: PoseInput | None = None
    error: LiftError | None = None  # why it has no pose (its layout, its threshold, its fps)
    track_id: str = ""
    fps: float = 0.0  # frames per second, given for tracked poses
    people: tuple[PersonIn, ...] | None = None  # a frame of several people instead of `pose`
    model: str = ""  # the id of the model that lifts it (a known one; empty: the default)

    def persons(self) -> tuple[PersonIn, ...]:
        """Its people: `people`, or the one of `pose`; none when the frame has an error."""
        if self.error is not None:
            return ()
        if self.people is not None:
            return self.people
        return (PersonIn(self.track_id, POSE_FIELD, self.pose),)


@dataclass(frozen=True)
class Answer:
    """One frame's outcome: for a frame of one pose, its row of the group's replies or why it has
    none; for a frame of several people, each one's (`people`), or why the frame has none."""

    frame: FrameIn
    outcome: int | LiftError | None  # None: a frame of several people without an error of its own
    people: tuple[int | LiftError, ...] = ()

    @property
    def error(self) -> LiftError | None:
        """The frame's error, else its first person's (what the frame is counted as)."""
        if isinstance(self.outcome, LiftError):
            return self.outcome
        return next((o for o in self.people if isinstance(o, LiftError)), None)


@dataclass(frozen=True)
class Answers:
    """A group's answers in frame order, and the replies their rows point into."""

    items: list[Answer]
    replies: Replies | None


@dataclass
class Group:
    """Frames taken together: prepared in one call, lifted as one engine request, answered together."""

    frames: list[FrameIn]
    prepared: Prepared | None = None  # the input rules' outcome for the frames that have a pose
    futures: list[Future[Any]] = field(default_factory=list)  # its job's runs (one, or one a part)
    # Once every future is done: the encoded answers (LiftBatcher.answer); None: its job was not queued.
    answer: Callable[[], Awaitable[Any]] | None = None
    failure: LiftError | None = None  # why its valid poses get no reply (queue full, a failed run)
    temporal: TemporalRows | None = None  # the temporal model's answers to its tracked poses

    @property
    def model(self) -> str:
        """The model of its frames (a group holds one model's frames: StreamState.take)."""
        return self.frames[0].model

    def done(self) -> bool:
        """Every run of the group has finished (a group without runs at once)."""
        return all(f.done() for f in self.futures)

    def poses(self) -> list[PoseInput]:
        """The poses to lift, frame by frame and person by person."""
        return [p.pose for f in self.frames for p in f.persons() if p.pose is not None]

    def tracked(self) -> list[TrackedPose | None]:
        """Per pose of poses(), its track (None: an untracked pose, lifted alone)."""
        return [
            TrackedPose(p.track_id, f.frame_id, f.fps, p.field) if p.track_id else None
            for f in self.frames
            for p in f.persons()
            if p.pose is not None
        ]

    def valid(self) -> list[tuple[FrameIn, PersonIn, int]]:
        """Every person whose pose passed the input rules, with its row of the valid poses."""
        violations = iter(self.prepared.violations if self.prepared is not None else ())
        found, row = [], 0
        for frame in self.frames:
            for person in frame.persons():
                if person.pose is not None and not next(violations):
                    found.append((frame, person, row))
                    row += 1
        return found

    def _outcome(self, replies: Replies | None, row: int, errors: dict[int, LiftError]) -> int | LiftError:
        """A valid pose's outcome: its row of `replies`, or why its run or its track failed."""
        if self.failure is not None:
            return self.failure
        if row in errors:
            return errors[row]
        if replies is None:
            raise ValueError("a group's valid poses are answered with replies or a failure")
        return ModelOutputError([row]) if replies.failed[row] else row  # stand-ins are never sent

    def answers(self, replies: Replies | None, errors: dict[int, LiftError] | None = None) -> list[Answer]:
        """Each frame's answer, in order: why it has no pose, else per person its pose's
        violations, else why its run (or its track: `errors` by row) failed, else its row of
        `replies` (the replies of the valid poses, in order)."""
        violations = iter(self.prepared.violations if self.prepared is not None else ())
        answers: list[Answer] = []
        row = 0  # the next valid pose's row
        for frame in self.frames:
            if frame.error is not None:
                answers.append(Answer(frame, frame.error))
                continue
            outcomes: list[int | LiftError] = []
            for person in frame.persons():
                if person.error is not None:
                    outcomes.append(person.error)
                elif found := next(violations):
                    outcomes.append(InvalidKeypoints([v.within(person.field) for v in found]))
                else:
                    outcomes.append(self._outcome(replies, row, errors or {}))
                    row += 1
            if frame.people is None:
                answers.append(Answer(frame, outcomes[0]))
            else:
                answers.append(Answer(frame, None, tuple(outcomes)))
        return answers
