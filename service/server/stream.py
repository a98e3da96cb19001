"""Streams: one stream's frames from read to answer, in order, within a bounded window (no wire format)."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections import deque
from collections.abc import AsyncGenerator, AsyncIterator, Callable, Hashable
from functools import partial
from typing import TypeVar

from repnet.core.errors import LiftError, ModelOutputError
from repnet.core.inputs import Limits
from repnet.core.keypoints import prepare_poses
from repnet.runtime.batcher import offload, settle
from repnet.runtime.batchers import LiftBatcher
from repnet.runtime.catalog import Catalog
from repnet.runtime.pipeline import TRACKED_COST, Job, Lifted, StreamTracks
from repnet.runtime.plans import TemporalModels
from repnet.runtime.tracks import TrackTable
from repnet.server.frames import POSE_FIELD, Answer, Answers, FrameIn, Group, PersonIn

__all__ = ["POSE_FIELD", "Answer", "Answers", "FrameIn", "Group", "PersonIn", "StreamIdle", "UnreadableFrame"]

log = logging.getLogger(__name__)

# A group that finds the batch queue full waits this long for room before its frames get an error:
# the window already bounds what a stream holds, so a busy moment slows it down instead.
QUEUE_WAIT_S = 5.0
R = TypeVar("R")  # what a transport encodes a group's answers as


class StreamIdle(Exception):
    """Nothing was in progress and no frame came for the idle timeout: the stream is closed."""


class UnreadableFrame(Exception):
    """A frame could not be read; every frame before it has been answered, and the stream ends."""


class StreamState:
    """What one stream holds: frames read and not taken yet, then groups taken and not answered yet.

    At most `window` poses are held from read to answer (the reader waits for room: backpressure):
    a frame counts its people (at least 1), so the bound is in what a client sends, however many
    people its frames carry. The last frame read may pass it, so a stream holds fewer than `window`
    plus one frame's people (REPNET_MAX_REQUEST_POSES).
    Frames are taken only while none of the stream's groups waits for a run, so the frames that
    arrive during a run become the next groups (at most `max_group` of cost each, a tracked person
    counting TRACKED_COST as in runtime.pipeline.job_cost; a frame with more a group of its own; a
    frame for another model than the frame before starts a new group):
    the cost per frame stays small, and one stream fills batches instead of waiting for each
    frame's run. Counting poses, not frames, keeps every group within the batch queue, however many
    people its frames carry.
    """

    def __init__(self, window: int, max_group: int) -> None:
        if window < 1 or max_group < 1:
            raise ValueError(f"window and max_group must be >= 1, got {window} and {max_group}")
        self.window = window
        self.max_group = max_group
        self.inbox: list[FrameIn] = []  # read, not taken
        self.groups: deque[Group] = deque()  # taken, not answered, in order
        self.held = 0  # poses of the frames read and not answered

    def has_room(self) -> bool:
        """Another frame may be read."""
        return self.held < self.window

    def add(self, frame: FrameIn) -> None:
        """Hold a frame just read; ValueError when the window is full (read only while has_room())."""
        if not self.has_room():
            raise ValueError(f"the window of {self.window} poses is full")
        self.inbox.append(frame)
        self.held += held_poses(frame)

    def can_take(self) -> bool:
        """Frames wait, and none of this stream's groups waits for a run."""
        return bool(self.inbox) and (not self.groups or self.groups[-1].done())

    def take(self) -> list[Group]:
        """Every frame read so far, as the next groups of at most max_group poses (queued behind the
        earlier ones)."""
        frames, self.inbox = self.inbox, []
        groups: list[Group] = []
        taken: list[FrameIn] = []
        poses = 0.0  # their cost
        for frame in frames:
            count = frame_cost(frame)
            if taken and (poses + count > self.max_group or frame.model != taken[-1].model):
                groups.append(Group(taken))
                taken, poses = [], 0
            taken.append(frame)
            poses += count
        if taken:
            groups.append(Group(taken))
        self.groups.extend(groups)
        return groups

    def answerable(self) -> Group | None:
        """The oldest group, once its runs have finished: answers leave in the order frames came."""
        return self.groups[0] if self.groups and self.groups[0].done() else None

    def answered(self, group: Group) -> None:
        """The oldest group's answers have been sent: its frames leave the window."""
        if not self.groups or self.groups[0] is not group:
            raise ValueError("groups are answered oldest first")
        self.groups.popleft()
        self.held -= sum(held_poses(frame) for frame in group.frames)


def frame_cost(frame: FrameIn) -> float:
    """A frame's share of a run (runtime.pipeline.job_cost): its people, a tracked one TRACKED_COST."""
    people = frame.persons()
    tracked = sum(1 for p in people if p.track_id)
    return len(people) + (TRACKED_COST - 1.0) * tracked


def held_poses(frame: FrameIn) -> int:
    """What a frame counts in a stream's window: its people, and 1 for a frame of none (an error)."""
    return max(1, len(frame.persons()))


async def _start(
    group: Group,
    models: Catalog,
    transport: str,
    tracks: StreamTracks | None,
    encode: Callable[[Answers], R],
    source: Hashable,
) -> None:
    """Queue the group's poses as one job of the group's model: its batch runs the input rules, the
    model, the stream's tracks and causal model, and encodes the group's answers (a frame of more
    people than a run holds is queued in parts: LiftBatcher.queue_async)."""
    engine = models.engines.get(group.model) or models.default_engine  # frames name known models
    poses, tracked = group.poses(), group.tracked() if tracks is not None else []
    if not poses:
        return
    job = Job(
        finish=partial(_answer, group, encode),
        poses=poses,
        tracks=tracks if any(t is not None for t in tracked) else None,
        tracked=tracked if tracks is not None else (),
        track_ids=[t.track_id if t is not None else None for t in tracked] if tracked else None,
    )
    try:
        group.futures = await engine.queue_async(job, transport, wait_s=QUEUE_WAIT_S, source=source)
        group.answer = partial(engine.answer, job, group.futures)
    except LiftError as err:  # queue full for too long, or shutting down
        group.failure = err.as_answer()


async def _finish(group: Group, encode: Callable[[Answers], R], limits: Limits) -> R:
    """The encoded answers of a group whose job has finished (its batch encoded them); a failed job
    fails its frames, not the stream (their poses' own rules still answered, off the event loop)."""
    # The job's finish holds the group: taking its answer out leaves no cycle for the collector.
    answer, group.answer = group.answer, None
    if answer is not None and group.failure is None:
        try:
            answered: R = await answer()
            return answered
        except LiftError as err:
            group.failure = err.as_answer()
        except Exception:  # one run's fault must not end the stream
            log.exception("stream frames %d..: lifting failed", group.frames[0].frame_id)
            group.failure = LiftError("internal error while lifting this frame")
    return await offload(len(group.frames), _refused, group, limits, encode)


def _answer(group: Group, encode: Callable[[Answers], R], lifted: Lifted) -> R:
    """A group's answers from what its job got (on the batcher's thread), encoded."""
    group.prepared = lifted.prepared
    replies = lifted.replies
    if replies is not None and replies.failed.any():  # counted as each frame is answered; one line
        first = group.frames[0].frame_id
        log.error("stream frames %d..: %s", first, ModelOutputError(replies.failed.nonzero()[0].tolist()))
    return encode(Answers(group.answers(replies, lifted.errors), replies))


def _refused(group: Group, limits: Limits, encode: Callable[[Answers], R]) -> R:
    """The answers of a group whose job did not run or failed: each pose's own violations, else
    the group's failure."""
    poses = group.poses()
    if group.prepared is None and poses:
        group.prepared = prepare_poses(poses, limits)
    return encode(Answers(group.answers(None, {}), None))


class _Reader:
    """Reads a stream's frames into its StreamState while the window has room, and wakes the loop
    that answers them: when a frame arrives, a run finishes or the frames end."""

    def __init__(self, frames: AsyncIterator[FrameIn], state: StreamState) -> None:
        self.state = state
        self.wake = _Waker()  # something may be actionable
        self.ended = False  # no frame will come any more
        self.unreadable: Exception | None = None  # why the frames ended, if they failed
        self._room = asyncio.Event()  # a group was answered: the window may have room again
        self._quiet_since: float | None = None  # time.monotonic() since nothing is in progress
        self._loop = asyncio.get_running_loop()
        self._task = asyncio.create_task(self._read(frames))

    async def _read(self, frames: AsyncIterator[FrameIn]) -> None:
        try:
            async for frame in frames:
                self.state.add(frame)
                self.wake.set()
                while not self.state.has_room():
                    self._room.clear()
                    await self._room.wait()
        except Exception as err:  # what cannot be read ends the stream once the rest is answered
            self.unreadable = err
        finally:  # the client half-closed, cancelled or the call failed: nothing more to read
            self.ended = True
            self.wake.set()

    def watch(self, group: Group) -> None:
        """Wake the loop when the group's runs finish (on the engine's thread)."""
        for future in group.futures:
            future.add_done_callback(self._on_done)

    def _on_done(self, _: object) -> None:
        with contextlib.suppress(RuntimeError):  # the loop closed: the server has stopped
            self._loop.call_soon_threadsafe(self.wake.set)

    def answered(self, group: Group) -> None:
        """The oldest group's answers were sent: its frames make room in the window."""
        self.state.answered(group)
        self._room.set()

    async def next_event(self, idle_timeout_s: float, tick_s: float | None = None) -> None:
        """Wait until something may be actionable, or at most `tick_s` (the caller's timers);
        StreamIdle when nothing is in progress and no frame comes for `idle_timeout_s` (ticks do
        not count as frames)."""
        if self.state.can_take() or self.state.answerable() is not None:
            self._quiet_since = None
            return
        if self.state.held or self.ended:
            self._quiet_since = None
            await self.wake.wait(tick_s)
            return
        now = time.monotonic()
        if self._quiet_since is None:
            self._quiet_since = now
        remaining = self._quiet_since + idle_timeout_s - now
        if remaining <= 0:
            raise StreamIdle(f"no frame for {idle_timeout_s:g} s")
        await self.wake.wait(remaining if tick_s is None else min(remaining, tick_s))

    def close(self) -> None:
        """Stop reading."""
        self._task.cancel()


async def answer_stream(
    frames: AsyncIterator[FrameIn],
    engine: LiftBatcher | Catalog,
    limits: Limits,
    encode: Callable[[Answers], R],
    *,
    window: int,
    idle_timeout_s: float,
    transport: str,
    temporal: TemporalModels | None = None,
    source: Hashable = None,
) -> AsyncGenerator[R, None]:
    """Read `frames` and yield their answers group by group, in frame order (see StreamState), as
    encode(answers) gives them: the transport's results, built off the event loop with the replies.

    Raises StreamIdle when nothing is in progress and no frame comes for `idle_timeout_s`, and
    UnreadableFrame (after answering the frames before it) when `frames` fails. With a causal
    temporal model, tracked poses are answered from their track's frames so far; a track without
    a frame for the tracks' idle_s is dropped (whether the stream sends other frames or none), and
    the stream's tracks are freed when it ends. `source`: who sends the stream (its connection), for
    the batch queue's fair share (None: the stream itself).
    """
    source = object() if source is None else source
    models = Catalog.of(engine, temporal is not None)
    reader = _Reader(frames, StreamState(window, models.default_engine.max_batch))
    state = reader.state
    table = None if temporal is None else temporal.table()
    causal = None if temporal is None else temporal.engines.get("causal")
    tracks = None if table is None or causal is None else StreamTracks(table, causal.lifter)
    try:
        while True:
            reader.wake.clear()
            if state.can_take():
                for taken in state.take():
                    await _start(taken, models, transport, tracks, encode, source)
                    reader.watch(taken)
            while (group := state.answerable()) is not None:
                yield await _finish(group, encode, limits)
                reader.answered(group)
            if reader.ended and not state.held:
                if reader.unreadable is not None:
                    raise UnreadableFrame(str(reader.unreadable)) from reader.unreadable
                return
            if table is not None:  # tracks without a frame for idle_s go, frames or not
                table.expire()
            await reader.next_event(idle_timeout_s, tick_s=_tick(table))
    finally:
        reader.close()
        if table is not None:
            table.close()


def _tick(table: TrackTable | None) -> float | None:
    """How often a stream must look at its tracks' idle times: half of idle_s while it holds any."""
    return table.idle_s / 2 if table is not None and table.tracks else None


class _Waker:
    """An event for one waiting task, whose timed wait needs no task of its own (asyncio.wait_for
    makes one per wait, and a paced stream waits once a frame)."""

    def __init__(self) -> None:
        self._set = False
        self._waiter: asyncio.Future[None] | None = None

    def set(self) -> None:
        """Something may be actionable: wake the waiting task."""
        self._set = True
        if self._waiter is not None:
            settle(self._waiter)

    def clear(self) -> None:
        """Nothing new since now."""
        self._set = False

    async def wait(self, timeout_s: float | None = None) -> None:
        """Until set, or at most `timeout_s`."""
        if self._set:
            return
        loop = asyncio.get_running_loop()
        self._waiter = waiter = loop.create_future()
        timer = None if timeout_s is None else loop.call_later(timeout_s, settle, waiter)
        try:
            await waiter
        finally:
            self._waiter = None
            if timer is not None:
                timer.cancel()
