"""bench.paced_pass: the idle gap before a call is not counted in its cost, and the passes it times
are the service's (a tracked pose answered from its track)."""

from __future__ import annotations

import numpy as np

from bench.paced_pass import GAPS, Calls, thread_cpu_ms
from repnet.runtime.temporal import TemporalLifter
from repnet.server.config import Settings
from repnet.server.startup import load_lifter


def test_a_spinning_gap_is_not_counted_in_the_calls_cost() -> None:
    spent = thread_cpu_ms(lambda: None, calls=5, gap_s=0.02, idle=GAPS["spinning"])
    assert spent < 1.0  # ms: each call is nothing; the 20 ms of spinning before it is not counted


def test_the_tracked_pass_is_answered_from_its_track() -> None:
    settings = Settings(intra_op_threads=1)
    calls = Calls(load_lifter(settings), TemporalLifter.load(settings.causal_model_path, settings))
    tracked = calls.pass_of(True)
    for _ in range(3):
        tracked()
    track = calls.tracks.table.tracks["person"]
    assert track.stored == 3 and track.last_frame == calls.frame == 3
    job = calls.pass_of(False)
    job()  # an untracked pose leaves the track alone
    assert track.stored == 3
    assert np.isfinite(calls.lifter.session.run(None, calls.pose_feed)[0]).all()
