"""bench.profile's reading of py-spy's collapsed stacks."""

from __future__ import annotations

from bench.profile import Profile

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
