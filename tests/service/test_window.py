"""Expected company: when a regular sender (a paced camera) sends next, and a batcher that holds a
run for it (runtime.window)."""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
import pytest

from repnet.core.inputs import ModelInput, PoseInput
from repnet.core.keypoints import prepare_poses
from repnet.runtime import window
from repnet.runtime.batchers import LiftBatcher
from repnet.runtime.lifter import Lifter
from repnet.runtime.window import Arrivals
from repnet.server.app import limits_of
from repnet.server.config import Settings
from tests.conftest import POSE_2D, GatedLifter


def test_a_paced_source_is_expected_one_period_after_its_last_arrival() -> None:
    found = Arrivals()
    for k in range(5):
        found.arrived("camera", 10.0 + k / 30)
    last = 10.0 + 4 / 30
    due = found.expected(last + 0.001, last + 0.1)
    assert due == pytest.approx(last + 1 / 30 + window.SLACK_S + window.SLACK_SHARE / 30)
    assert found.expected(last + 0.001, last + 0.02) is None  # not by then
    assert found.expected(last + 0.001, last + 0.1, queued={"camera"}.__contains__) is None  # already queued


def test_one_arrival_a_long_gap_or_a_late_source_is_not_expected() -> None:
    found = Arrivals()
    found.arrived("once", 0.0)
    assert found.expected(0.001, 5.0) is None  # no period yet
    found.arrived("gap", 0.0)
    found.arrived("gap", window.HORIZON_S + 0.1)  # a pause, not a period
    assert found.expected(window.HORIZON_S + 0.2, 9.0) is None
    found.arrived("late", 1.0)
    found.arrived("late", 1.1)  # due at 1.2
    assert found.expected(1.2 + 0.04, 9.0) == pytest.approx(1.24 + window.SLACK_S + 0.01)  # late: now
    assert found.expected(1.2 + 0.06, 9.0) is None  # more than LATE of its period late: gone quiet


def test_a_busy_batcher_waits_for_expected_company_until_enough_poses_wait() -> None:
    """Paced cameras that each run alone keep a batcher busy; it still holds a run for a camera due
    within company_wait_s (before 2026-12-06 a batcher busy half of its time did not, and 8 cameras
    on one worker ran one frame a run). Once COMPANY_ENOUGH poses wait, the run is due. Under load
    (work queued during the last run), the load's window applies instead of expected company."""
    timing = window.Window(max_wait_s=0.004, company_wait_s=0.012)
    timing.busy = 0.9
    timing.arrived("camera", 1.000)
    timing.arrived("camera", 1.010)  # every 10 ms: due at 1.020
    deadline, company = timing.deadlines(1.015, loaded=False)
    assert deadline == 1.015 and company == pytest.approx(1.027)
    nothing = {}.__contains__  # no source has anything queued
    expected = 1.020 + window.SLACK_S + window.SLACK_SHARE * 0.010
    assert timing.due(1.015, deadline, company, nothing, 1) == pytest.approx(expected)
    assert timing.due(1.015, deadline, company, nothing, window.COMPANY_ENOUGH - 1) == pytest.approx(expected)
    assert timing.due(1.015, deadline, company, nothing, window.COMPANY_ENOUGH) == deadline
    deadline, company = timing.deadlines(1.015, loaded=True)
    assert company == 1.015 and deadline == pytest.approx(1.015 + window.batch_window(0.004, 0.9))
    assert timing.due(1.015, deadline, company, nothing, 1) == deadline


def test_the_sources_followed_are_bounded_and_swept() -> None:
    found = Arrivals()
    for k in range(window.MAX_SOURCES + 100):
        found.arrived(k, 0.0)
    assert len(found) == window.MAX_SOURCES
    found.sweep(window.HORIZON_S + 1.0)
    assert len(found) == 0
    for k in range(window.SWEEP_EVERY):  # the sweep also runs by itself
        found.arrived(("new", k), 10.0)
    assert len(found) == window.SWEEP_EVERY


def inputs(i: int) -> ModelInput:
    pose = POSE_2D * (1 + 0.05 * i) + [7 * i, -3 * i]
    return prepare_poses([PoseInput(pose, np.ones(17, bool))], limits_of(Settings())).check()


def test_paced_sources_share_runs_and_a_lone_waiting_client_is_not_held(
    engine_factory: Callable[..., LiftBatcher], gated: GatedLifter, lifter: Lifter
) -> None:
    """Two sources sending every 50 ms, 10 ms apart: with company_wait_s the first of each pair waits
    for the second and they share a run; without it, each runs alone. A client that waits for each
    answer is never waited for."""

    def paced(engine: LiftBatcher) -> list[int]:
        sources = [object(), object()]
        start = time.monotonic()
        futures = []
        for k in range(12):
            for s, offset in enumerate((0.0, 0.010)):
                delay = start + 0.05 * k + offset - time.monotonic()
                time.sleep(max(0.0, delay))
                futures += engine.submit(inputs(2 * k + s), "grpc", source=sources[s])
        for f in futures:
            f.result(timeout=10)
        return gated.batches[-24:]

    alone = paced(engine_factory(gated, max_batch=64, max_wait_s=0.0, queue_size=64))
    assert max(alone) == 1
    gated.batches.clear()
    engine = engine_factory(gated, max_batch=64, max_wait_s=0.0, queue_size=64)
    engine.window.company_wait_s = 0.030
    shared = paced(engine)
    assert shared.count(2) >= 8  # after the first periods are learnt, every pair shares a run

    engine = engine_factory(lifter, max_batch=64, max_wait_s=0.0, queue_size=64)
    engine.window.company_wait_s = 5.0
    client = object()
    for k in range(5):  # closed loop: its next request comes only after its answer
        start = time.monotonic()
        engine.submit(inputs(k), "http", source=client)[0].result(timeout=10)
        assert time.monotonic() - start < 1.0
