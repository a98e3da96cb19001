"""Stream bookkeeping without a server: the window, groups, answers in order, idle and unreadable streams."""

from __future__ import annotations

import asyncio
import gc
import time
import weakref
from collections.abc import AsyncIterator, Callable
from concurrent.futures import Future
from dataclasses import replace

import numpy as np
import pytest

from repnet.core.errors import InvalidKeypoints, LiftError, ModelNotReady, Violation
from repnet.core.inputs import Limits, PoseInput
from repnet.core.keypoints import prepare_poses
from repnet.runtime.batchers import LiftBatcher
from repnet.runtime.catalog import Catalog
from repnet.runtime.lifter import Lifter
from repnet.runtime.pipeline import TRACKED_COST, Job
from repnet.runtime.replies import build_replies
from repnet.server.stream import (
    Answer,
    Answers,
    FrameIn,
    Group,
    PersonIn,
    StreamIdle,
    StreamState,
    UnreadableFrame,
    _finish,
    _Reader,
    _start,
    answer_stream,
    frame_cost,
)
from tests.conftest import POSE_2D, GatedLifter


def pose(i: int) -> PoseInput:
    return PoseInput(POSE_2D + [5.0 * i, -2.0 * i], np.ones(17, bool))


def frame(i: int, error: LiftError | None = None) -> FrameIn:
    return FrameIn(i, time.perf_counter(), None if error else pose(i), error)


def same(answers: Answers) -> Answers:
    """The encoding a transport would give the answers: here none."""
    return answers


def outcomes(answers: list[Answer]) -> list[int | str]:
    """Each answer's row, or its error's class name."""
    return [a.outcome if isinstance(a.outcome, int) else type(a.outcome).__name__ for a in answers]


def test_the_window_bounds_what_a_stream_holds_from_read_to_answer() -> None:
    state = StreamState(window=3, max_group=2)
    for i in range(3):
        assert state.has_room()
        state.add(frame(i))
    assert not state.has_room()
    with pytest.raises(ValueError, match="window of 3 poses is full"):
        state.add(frame(3))
    first, second = state.take()  # every frame read, in groups of at most max_group
    assert [f.frame_id for f in first.frames] == [0, 1] and [f.frame_id for f in second.frames] == [2]
    assert not state.has_room()  # taken is not answered
    with pytest.raises(ValueError, match="oldest first"):
        state.answered(second)
    assert state.answerable() is first  # no run: done at once
    state.answered(first)
    assert state.held == 1 and state.has_room() and state.answerable() is second


def test_the_window_counts_the_poses_of_frames_of_many_people() -> None:
    """A frame of 3 people takes 3 of the window's poses; the window may be passed by the last frame
    read only, and answering a group gives back what its frames took."""
    state = StreamState(window=4, max_group=6 * TRACKED_COST)  # 2 frames of 3 tracked people
    state.add(crowd(0, 3))
    assert state.held == 3 and state.has_room()
    state.add(crowd(1, 3))  # read while there was room: 6 held, no more reads
    assert state.held == 6 and not state.has_room()
    (group,) = state.take()
    state.answered(group)
    assert state.held == 0 and state.has_room()
    state.add(frame(2, error=ModelNotReady("x")))  # a frame without people counts one
    assert state.held == 1


def test_a_group_holds_the_frames_of_one_model() -> None:
    state = StreamState(window=8, max_group=8)
    for i, model in enumerate(["a", "a", "b", "a", ""]):
        state.add(replace(frame(i), model=model))
    groups = state.take()  # a run is of one model: a frame for another starts a new group
    assert [[f.frame_id for f in g.frames] for g in groups] == [[0, 1], [2], [3], [4]]
    assert [g.model for g in groups] == ["a", "b", "a", ""]


def test_frames_read_during_a_run_wait_for_it_and_become_the_next_group() -> None:
    state = StreamState(window=8, max_group=8)
    state.add(frame(0))
    (running,) = state.take()
    running.futures = [Future()]  # its run has not finished
    state.add(frame(1))
    state.add(frame(2))
    assert not state.can_take() and state.answerable() is None
    running.futures[0].set_result(None)
    assert state.can_take() and state.answerable() is running
    (following,) = state.take()
    assert [f.frame_id for f in following.frames] == [1, 2]


def test_a_groups_answers_follow_its_frames(lifter: Lifter, limits: Limits) -> None:
    """One index space: each frame in order gets why it has no pose, its pose's violations (named
    within `pose`), its run's failure, or the next row of the replies."""
    bad = replace(pose(2), points=np.full((17, 2), np.nan))
    unreadable = InvalidKeypoints(
        [Violation("pose.keypoints", "expected 2 values (x, y) per joint", "joint_count")]
    )
    frames = [frame(0), frame(1, error=unreadable), replace(frame(2), pose=bad), frame(3), frame(4)]
    group = Group(frames, prepare_poses([f.pose for f in frames if f.pose is not None], limits))
    inputs = group.prepared.inputs if group.prepared else None
    assert inputs is not None and len(inputs) == 3
    prediction = lifter.lift(inputs.keypoints_2d, inputs.visible)
    replies = build_replies(inputs, replace(prediction, failed=np.array([False, True, False])))
    answers = group.answers(replies)
    assert [a.frame.frame_id for a in answers] == [0, 1, 2, 3, 4]
    assert outcomes(answers) == [0, "InvalidKeypoints", "InvalidKeypoints", "ModelOutputError", 2]
    assert answers[1].outcome is unreadable
    named = answers[2].outcome
    assert isinstance(named, InvalidKeypoints) and named.violations[0].field == "pose.keypoints[0]"
    group.failure = ModelNotReady("shutting down")
    assert (
        outcomes(group.answers(None))
        == ["ModelNotReady", "InvalidKeypoints", "InvalidKeypoints"] + ["ModelNotReady"] * 2
    )


async def source(
    frames: list[FrameIn],
    pulled: list[int],
    pause: asyncio.Event | None = None,
    fail: Exception | None = None,
) -> AsyncIterator[FrameIn]:
    """Yield `frames` (the first alone, the rest once `pause` is set), recording each frame pulled;
    then raise `fail`, if given."""
    for k, f in enumerate(frames):
        if k == 1 and pause is not None:
            await pause.wait()
        pulled.append(f.frame_id)
        yield f
    if fail is not None:
        raise fail


async def collect(groups: AsyncIterator[Answers]) -> list[Answer]:
    return [answer async for group in groups for answer in group.items]


async def until(condition: Callable[[], bool]) -> None:
    deadline = time.monotonic() + 10
    while not condition():
        assert time.monotonic() < deadline, "timed out"
        await asyncio.sleep(0.005)


def test_a_stream_is_answered_in_order_and_fills_batches(
    engine_factory: Callable[..., LiftBatcher], gated: GatedLifter, limits: Limits
) -> None:
    """The frames that arrive while a run is in progress are lifted together after it, in groups of
    at most max_batch, and every frame gets the answer to its own pose."""
    engine = engine_factory(gated, max_batch=4, queue_size=64)
    frames = [frame(i) for i in range(7)]

    async def scenario() -> list[Answer]:
        pulled: list[int] = []
        more = asyncio.Event()
        stream = answer_stream(
            source(frames, pulled, more), engine, limits, same, window=16, idle_timeout_s=30, transport="test"
        )
        gated.gate.clear()
        answered = asyncio.create_task(collect(stream))
        await until(gated.entered.is_set)  # frame 0 is in its run
        more.set()
        await until(lambda: len(pulled) == 7)
        gated.gate.set()
        return await answered

    answers = asyncio.run(scenario())
    assert [a.frame.frame_id for a in answers] == list(range(7))
    assert gated.batches == [1, 4, 2]
    assert all(isinstance(a.outcome, int) for a in answers)


def crowd(i: int, people: int) -> FrameIn:
    persons = tuple(PersonIn(f"t{k}", f"people[{k}].pose", pose(i + k)) for k in range(people))
    return FrameIn(i, time.perf_counter(), fps=30.0, people=persons)


def test_groups_count_poses_so_that_frames_of_many_people_fit_the_queue() -> None:
    state = StreamState(window=32, max_group=4 * TRACKED_COST)  # 4 tracked people, 16 untracked
    frames = [crowd(0, 3), crowd(1, 2), crowd(2, 5), frame(3), frame(4), frame(5, error=ModelNotReady("x"))]
    for f in frames:
        state.add(f)
    groups = state.take()  # a frame of more than max_group's cost is a group of its own
    assert [[f.frame_id for f in g.frames] for g in groups] == [[0], [1], [2], [3, 4, 5]]
    assert [len(g.poses()) for g in groups] == [3, 2, 5, 2]


def test_a_tracked_person_counts_as_tracked_cost_poses_in_a_group() -> None:
    """A run holds at most max_batch of cost, so that one run of tracked poses stays short."""
    state = StreamState(window=64, max_group=2 * TRACKED_COST)
    for i in range(4):
        state.add(crowd(i, 1))  # one tracked person: cost TRACKED_COST
    for i in range(4, 12):
        state.add(frame(i))  # one untracked pose: cost 1
    groups = state.take()
    assert [[f.frame_id for f in g.frames] for g in groups] == [[0, 1], [2, 3], [4, 5, 6, 7, 8, 9, 10, 11]]
    assert frame_cost(crowd(0, 3)) == 3 * TRACKED_COST and frame_cost(frame(0)) == 1


def test_a_stream_of_many_people_per_frame_is_answered_within_the_queue(
    engine_factory: Callable[..., LiftBatcher], gated: GatedLifter, limits: Limits
) -> None:
    """Frames of 3 people that pile up during a run are lifted in groups of at most max_batch
    poses, never more than the queue holds (it refused them all at once before)."""
    engine = engine_factory(gated, max_batch=8, queue_size=16)
    frames = [crowd(i, 3) for i in range(12)]

    async def scenario() -> list[Answer]:
        pulled: list[int] = []
        more = asyncio.Event()
        stream = answer_stream(
            source(frames, pulled, more), engine, limits, same, window=48, idle_timeout_s=30, transport="t"
        )
        gated.gate.clear()
        answered = asyncio.create_task(collect(stream))
        await until(gated.entered.is_set)  # frame 0 is in its run
        more.set()
        await until(lambda: len(pulled) == 12)
        gated.gate.set()
        return await answered

    answers = asyncio.run(scenario())
    assert [a.frame.frame_id for a in answers] == list(range(12))
    assert all(isinstance(o, int) for a in answers for o in a.people), [a.error for a in answers]
    assert max(gated.batches) <= 8 and sum(gated.batches) == 36


def test_a_frame_of_more_people_than_a_run_holds_is_lifted_in_parts_and_another_client_waits_for_one(
    engine_factory: Callable[..., LiftBatcher], gated: GatedLifter, limits: Limits
) -> None:
    """A frame of 12 people with max_batch 4 is queued as 3 parts (before: one job whose 3 runs ran in
    one pass); a one-pose request of another client that comes during the first part's run runs
    next, and the frame is answered once, every person with its own pose's reply."""
    engine = engine_factory(gated, max_batch=4, queue_size=64)
    lone = Future[object]()

    async def scenario() -> list[Answer]:
        stream = answer_stream(
            source([crowd(0, 12)], []), engine, limits, same, window=16, idle_timeout_s=30, transport="t"
        )
        gated.gate.clear()
        answered = asyncio.create_task(collect(stream))
        await until(gated.entered.is_set)  # the frame's first part is in its run
        other = Job(finish=lambda lifted: lifted, poses=[pose(20)])
        (future,) = await engine.queue_async(other, "t", source="another client")
        future.add_done_callback(lambda f: lone.set_result(len(gated.batches)))
        gated.gate.set()
        return await answered

    answers = asyncio.run(scenario())
    assert gated.batches == [4, 1, 4, 4] and lone.result(1) == 2  # the other request ran second
    (answer,) = answers
    assert answer.people == tuple(range(12))  # each person's row of the replies, in order


def test_an_answered_group_is_freed_without_the_collector(engine: LiftBatcher, limits: Limits) -> None:
    """A group's job holds the group (its finish sets what the group got), and the group holds how
    to answer it until it is answered: then nothing is left in a cycle, so a stream's frames are
    freed as they are answered, not by the collector's full collections (which took 110-137 ms of
    a worker's interpreter lock each under 1,024-person frames)."""

    async def scenario() -> weakref.ref[Group]:
        group = Group([crowd(0, 3)])
        await _start(group, Catalog.of(engine, False), "t", None, same, "a client")
        await until(group.done)
        answers = await _finish(group, same, limits)
        assert answers.items[0].people == (0, 1, 2)  # each person its row of the replies
        return weakref.ref(group)

    gc.collect()
    gc.disable()
    try:
        group = asyncio.run(scenario())
        engine.run(Job(finish=lambda lifted: None, poses=[pose(1)]), "t")  # its thread's last batch goes
        assert group() is None
    finally:
        gc.enable()


def test_the_reader_stops_reading_when_the_window_is_full(
    engine_factory: Callable[..., LiftBatcher], gated: GatedLifter, limits: Limits
) -> None:
    engine = engine_factory(gated, max_batch=64, queue_size=64)
    frames = [frame(i) for i in range(10)]

    async def scenario() -> tuple[list[int], list[Answer]]:
        pulled: list[int] = []
        stream = answer_stream(
            source(frames, pulled), engine, limits, same, window=3, idle_timeout_s=30, transport="t"
        )
        gated.gate.clear()
        answered = asyncio.create_task(collect(stream))
        await until(gated.entered.is_set)
        await asyncio.sleep(0.2)
        held = list(pulled)  # no answer left: the reader waits for room
        gated.gate.set()
        return held, await answered

    held, answers = asyncio.run(scenario())
    assert held == [0, 1, 2]
    assert [a.frame.frame_id for a in answers] == list(range(10))


def test_an_unreadable_frame_ends_the_stream_after_the_frames_before_it(
    engine: LiftBatcher, limits: Limits
) -> None:
    got: list[Answer] = []

    async def scenario() -> None:
        failing = source([frame(0), frame(1)], [], fail=ValueError("bytes that are no frame"))
        async for group in answer_stream(
            failing, engine, limits, same, window=8, idle_timeout_s=30, transport="t"
        ):
            got.extend(group.items)

    with pytest.raises(UnreadableFrame) as raised:
        asyncio.run(scenario())
    assert [a.frame.frame_id for a in got] == [0, 1] and all(isinstance(a.outcome, int) for a in got)
    assert str(raised.value) == "bytes that are no frame"


def test_a_stream_without_frames_is_closed_as_idle(engine: LiftBatcher, limits: Limits) -> None:
    async def silent() -> AsyncIterator[FrameIn]:
        await asyncio.Event().wait()  # never sends, never ends
        yield frame(0)

    async def scenario() -> None:
        async for _ in answer_stream(
            silent(), engine, limits, same, window=8, idle_timeout_s=0.1, transport="t"
        ):
            pass

    start = time.monotonic()
    with pytest.raises(StreamIdle, match="no frame for 0.1 s"):
        asyncio.run(scenario())
    assert time.monotonic() - start < 5


def test_ticks_do_not_count_as_frames_for_the_idle_timeout() -> None:
    """A stream that wakes every tick (to drop its idle tracks) is still closed idle_timeout_s after
    its last frame, not a tick later each time."""

    async def silent() -> AsyncIterator[FrameIn]:
        await asyncio.Event().wait()
        yield frame(0)

    async def scenario() -> tuple[int, float, BaseException | None]:
        reader = _Reader(silent(), StreamState(window=4, max_group=4))
        ticks, start = 0, time.monotonic()
        try:
            while ticks < 100:
                await reader.next_event(0.5, tick_s=0.1)
                ticks += 1
        except StreamIdle as err:
            return ticks, time.monotonic() - start, err
        finally:
            reader.close()
        return ticks, time.monotonic() - start, None

    ticks, waited, closed = asyncio.run(scenario())
    assert isinstance(closed, StreamIdle) and ticks >= 3 and 0.45 < waited < 2.0


def test_frames_the_engine_refuses_get_its_error_and_the_stream_goes_on(
    engine: LiftBatcher, limits: Limits
) -> None:
    engine.close(timeout=10)

    async def scenario() -> list[Answer]:
        frames = source([frame(0), frame(1)], [])
        return await collect(
            answer_stream(frames, engine, limits, same, window=8, idle_timeout_s=30, transport="t")
        )

    assert outcomes(asyncio.run(scenario())) == ["ModelNotReady", "ModelNotReady"]
