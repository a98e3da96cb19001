"""When a batcher's next run is due: the batching window, which follows the load, and the company
expected from regular senders (a paced camera's next frame) that a run may wait for (runtime.batcher)."""

from __future__ import annotations

from collections.abc import Callable, Hashable
from dataclasses import dataclass

BUSY_TO_WAIT = 0.25  # a batcher busier than this share of its time lets requests wait for others
BUSY_SMOOTHING = 0.1  # the weight of the last run in the busy share (an average over ~10 runs)
# Queued poses with which a run waits for no more expected company. Both bundled models' runs cost
# per tracked pose 0.99 ms at batch 1, 0.60 at 2, 0.38 at 4, 0.27 at 8 and 0.17 at 64 (bench.
# temporal_load's roof, 2026-12-06): four poses take three quarters of what batching saves; waiting
# on for eight put 32 paced cameras' p99 over 25 ms (docs/BENCHMARKS.md).
COMPANY_ENOUGH = 4
HORIZON_S = 0.5  # a gap longer than this is not a period: the source starts again
SMOOTHING = 0.25  # the weight of the last gap in a source's period
LATE = 0.5  # a source later than this share of its period is not expected any more
SLACK_S = 0.001  # waited beyond an expected arrival (the sender's jitter), plus SLACK_SHARE of its period
SLACK_SHARE = 0.1
MAX_SOURCES = 4096  # sources followed at once; a new one beyond is not predicted
SWEEP_EVERY = 256  # arrivals between two sweeps of the sources heard of no more


def batch_window(max_wait_s: float, busy: float) -> float:
    """How long the oldest queued request may wait for others to join its batch, for a batcher that
    ran `busy` of its recent time: 0 up to BUSY_TO_WAIT, then in proportion, max_wait_s when always busy."""
    return max_wait_s * min(1.0, max(0.0, busy - BUSY_TO_WAIT) / (1.0 - BUSY_TO_WAIT))


def _none(source: Hashable) -> int:
    """Nothing queued, by any source."""
    return 0


@dataclass
class _Sender:
    last: float  # time.monotonic() of its last arrival
    period: float = 0.0  # its smoothed gap between arrivals (0: one arrival so far)


class Arrivals:
    """Each recent source's last arrival and smoothed period: when it is expected to send next.

    Memory: one entry per source heard of within HORIZON_S (swept every SWEEP_EVERY arrivals), at
    most MAX_SOURCES. Not thread-safe: the batcher calls it under its lock.
    """

    def __init__(self) -> None:
        self._senders: dict[Hashable, _Sender] = {}
        self._count = 0

    def __len__(self) -> int:
        return len(self._senders)

    def arrived(self, source: Hashable, now: float) -> None:
        """`source` sent something at `now`."""
        sender = self._senders.get(source)
        if sender is None:
            if len(self._senders) < MAX_SOURCES:
                self._senders[source] = _Sender(now)
        else:
            gap = now - sender.last
            if gap > HORIZON_S:
                sender.period = 0.0
            elif sender.period == 0.0:
                sender.period = gap
            else:
                sender.period += SMOOTHING * (gap - sender.period)
            sender.last = now
        self._count += 1
        if self._count % SWEEP_EVERY == 0:
            self.sweep(now)

    def sweep(self, now: float) -> None:
        """Forget the sources not heard of within HORIZON_S."""
        self._senders = {k: s for k, s in self._senders.items() if now - s.last <= HORIZON_S}

    def expected(self, now: float, until: float, queued: Callable[[Hashable], int] = _none) -> float | None:
        """The earliest time by `until` that a source with nothing `queued` (what it has queued) is
        expected to send, with its slack (a late one: now, while it is less than LATE of its
        period late); None if none is."""
        best: float | None = None
        for key, sender in self._senders.items():
            if sender.period <= 0.0 or queued(key):
                continue
            due = sender.last + sender.period
            if due < now - LATE * sender.period or due > until:
                continue
            due = max(due, now) + SLACK_S + SLACK_SHARE * sender.period
            if best is None or due < best:
                best = due
        return None if best is None else min(best, until)


class Window:
    """When a batcher's next run is due (not thread-safe: the batcher calls it under its lock).

    The window follows the load. A request that finds nothing queued after the last run runs at once
    (a client that waits for each answer never has company), unless a source with nothing queued is
    expected to send within company_wait_s of it (Arrivals: paced cameras' frames then share runs
    instead of each paying a run), until COMPANY_ENOUGH poses wait. However busy the batcher is:
    cameras that each run alone keep it busy, and only waiting for them makes their runs larger.
    When work queued during the last run, the oldest queued request may wait for more, up to
    batch_window(max_wait_s, the share of its time the batcher ran lately), so that runs grow with
    the load.
    """

    def __init__(self, max_wait_s: float, company_wait_s: float) -> None:
        if max_wait_s < 0 or company_wait_s < 0:
            raise ValueError("max_wait_s and company_wait_s must be >= 0")
        self.max_wait_s = max_wait_s
        self.company_wait_s = company_wait_s
        self.busy = 0.0  # the share of its time the batcher spent running, smoothed over recent runs
        self.arrivals = Arrivals()  # when the named sources are expected to send next

    def arrived(self, source: Hashable, now: float) -> None:
        """A named source queued work at `now` (a one-off request's source is not: it never returns)."""
        if self.company_wait_s > 0:
            self.arrivals.arrived(source, now)

    def ran(self, started: float, now: float, last_ended: float) -> None:
        """A run took started..now; the one before it ended at last_ended."""
        share = (now - started) / max(now - last_ended, 1e-9)  # of the time since the last run
        self.busy += BUSY_SMOOTHING * (share - self.busy)

    def deadlines(self, first: float, loaded: bool) -> tuple[float, float]:
        """For a queue whose oldest request came at `first`, and whether work queued during the last
        run: until when it waits for more (the load's window), and for expected company."""
        if loaded:  # under load, the load's window instead of expected company
            return first + batch_window(self.max_wait_s, self.busy), first
        return first, first + self.company_wait_s

    def due(
        self, now: float, deadline: float, company: float, queued: Callable[[Hashable], int], waiting: int
    ) -> float:
        """When the run is due: the load's deadline, or later while fewer than COMPANY_ENOUGH poses
        are `waiting` and a source with nothing `queued` (what it has queued) is expected to send by
        the company deadline."""
        if company <= now or waiting >= COMPANY_ENOUGH or not len(self.arrivals):
            return deadline
        expected = self.arrivals.expected(now, company, queued)
        return deadline if expected is None else max(deadline, expected)
