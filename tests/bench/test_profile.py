"""bench.profile's reading of py-spy's collapsed stacks, and of each thread's CPU from /proc."""

from __future__ import annotations

import os
import threading
import time

from bench.profile import Profile, thread_table
from bench.server import thread_cpu_seconds

RAW = """\
thread (1): MainThread;run (a.py:1);select (b.py:2) 5
thread (2): batcher;_run (e.py:3);lift (l.py:4);Session.run (o.py:5) 12
thread (2): batcher;_run (e.py:3);concat (e.py:9) 3
not a sample line
"""


def test_self_and_inclusive_shares_per_function_and_thread() -> None:
    profile = Profile.parse(RAW)
    assert profile.samples == 20
    assert profile.threads == {"thread (1): MainThread": 5, "thread (2): batcher": 15}
    assert profile.self_time["Session.run (o.py:5)"] == 12 and profile.self_time["lift (l.py:4)"] == 0
    assert profile.inclusive["_run (e.py:3)"] == 15 and profile.inclusive["lift (l.py:4)"] == 12
    assert "| `Session.run (o.py:5)` | 60.0 % |" in profile.table(profile.self_time, "function", top=1)


def test_a_recursive_frame_counts_once_per_sample() -> None:
    profile = Profile.parse("t;f (a:1);g (a:2);f (a:1) 4\n")
    assert profile.inclusive["f (a:1)"] == 4 and profile.self_time["f (a:1)"] == 4


def test_thread_names_are_read_with_or_without_the_process_frames() -> None:
    raw = 'process 7:"python -m repnet serve";process 9:"worker";thread (11): repnet-grpc;f (a:1) 2\n'
    assert Profile.parse(RAW + raw).names == {1: "MainThread", 2: "batcher", 11: "repnet-grpc"}


def test_a_threads_cpu_is_read_from_proc_and_counted_per_frame() -> None:
    me = threading.get_native_id()
    before = thread_cpu_seconds(os.getpid())
    end = time.thread_time() + 0.05
    while time.thread_time() < end:  # 50 ms of this thread's CPU
        pass
    after = thread_cpu_seconds(os.getpid())
    assert after[me][0] == os.getpid() and after[me][1] - before[me][1] >= 0.03  # clock ticks of 10 ms
    text, rows = thread_table(
        {me: (1, 0.0), 5: (1, 0.0)}, {me: (1, 0.5), 5: (1, 0.001)}, 2.0, 100.0, {me: "main"}
    )
    assert rows == [{"thread": "main", "tid": me, "pid": 1, "cores": 0.25, "ms_per_frame": 2.5}]  # 5: idle
    assert f"| `main` ({me}) | 1 | 0.250 | 2.500 |" in text
