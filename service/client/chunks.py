"""A clip too long for one temporal request, as several requests answered as the one would be.

A temporal request answers each tracked pose from its own track's frames around it (repnet.runtime.plans):
the frames `before` it (causal and offline) and `after` it (offline), Contract.reach. Tracks do not
see each other. So a clip of more poses than a request holds (`max_poses`) is sent as parts:
- whole tracks (and untracked poses) are packed, in order of appearance, into requests of at most
  `max_poses` poses;
- a track longer than that is cut into runs of consecutive frames, each sent with its context: the
  track's poses up to `before` frames before the run and up to `after` frames after it, and the next
  pose beyond each edge, so that a gap the service bridges there is filled from the same two poses;
  only the run's answers are kept.
Every window the temporal model reads is then the one it reads in a single request. One thing differs:
the service holds a track's answers to its bone lengths, the mean over the frames it was given of
the track (offline: of the segment; causal: so far), so a cut track's bones are the mean over its part
(under a millimetre from the single request's on the test clips: tests/service/test_cli.py).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TypeVar

import numpy as np

T = TypeVar("T")
Progress = Callable[[int], None]  # told how many poses each request answered


@dataclass(frozen=True)
class Part:
    """One request of a clip: which poses it sends, and which of their answers are kept."""

    send: np.ndarray  # (n,) int positions in the clip, increasing: the request's poses in order
    keep: np.ndarray  # (n,) bool: the answer is this pose's (not context); each pose is kept once

    def __len__(self) -> int:
        return len(self.send)


def runs(frames: np.ndarray, reach: tuple[int, int], max_poses: int) -> list[tuple[int, int, int, int]]:
    """Cut one track's increasing frame numbers into parts of at most `max_poses` poses: (first
    context, first kept, last kept, last context) indexes, the kept runs covering every pose once.
    ValueError when one pose and its context do not fit."""
    before, after = reach
    n = len(frames)
    # the pose at or beyond each edge: the last with frame <= f - before, the first with >= f + after
    left = np.maximum(np.searchsorted(frames, frames - before, side="right") - 1, 0)
    right = np.minimum(np.searchsorted(frames, frames + after, side="left"), n - 1)
    found = []
    start = 0
    while start < n:
        first = int(left[start])
        stop = int(np.searchsorted(right, first + max_poses - 1, side="right")) - 1  # last that fits
        if stop < start:
            raise ValueError(
                f"a request of {max_poses} poses cannot hold one frame's context ({before} frames "
                f"before, {after} after): raise the service's max_temporal_poses"
            )
        found.append((first, start, stop, int(right[stop])))
        start = stop + 1
    return found


def split_clip(
    track_ids: Sequence[str | None], frames: np.ndarray, reach: tuple[int, int], max_poses: int
) -> list[Part]:
    """The requests of a clip (`track_ids` and `frames` (N,) of its poses; an untracked pose has the
    track None) of at most `max_poses` poses each, for a model that reads `reach` frames around a
    frame; ValueError when a frame's context does not fit in one request."""
    if max_poses < 1:
        raise ValueError(f"max_poses must be at least 1, got {max_poses}")
    frames = np.asarray(frames, dtype=np.int64)
    groups: dict[object, list[int]] = {}
    for i, track in enumerate(track_ids):
        groups.setdefault(i if track is None else ("track", track), []).append(i)
    units: list[Part] = []
    for members in groups.values():
        mine = np.array(members, np.int64)
        mine = mine[np.argsort(frames[mine], kind="stable")]
        if len(mine) <= max_poses:
            units.append(Part(mine, np.ones(len(mine), bool)))
            continue
        for first, start, stop, last in runs(frames[mine], reach, max_poses):
            keep = np.zeros(last - first + 1, bool)
            keep[start - first : stop - first + 1] = True
            units.append(Part(mine[first : last + 1], keep))
    return _pack(units, max_poses)


def _pack(units: list[Part], max_poses: int) -> list[Part]:
    """Units into requests of at most max_poses, in order (a unit is never split); each request's
    poses in clip order."""
    requests: list[list[Part]] = []
    size = max_poses
    for unit in units:
        if size + len(unit) > max_poses:
            requests.append([])
            size = 0
        requests[-1].append(unit)
        size += len(unit)
    parts = []
    for members in requests:
        send = np.concatenate([u.send for u in members])
        keep = np.concatenate([u.keep for u in members])
        order = np.argsort(send, kind="stable")
        parts.append(Part(send[order], keep[order]))
    return parts


def assemble(count: int, parts: Sequence[Part], answers: Sequence[Sequence[T]]) -> list[T]:
    """The kept answers of every part at their poses' places: one per pose of the clip, in order."""
    out: list[T | None] = [None] * count
    filled = np.zeros(count, bool)
    for part, answer in zip(parts, answers, strict=True):
        if len(answer) != len(part):
            raise ValueError(f"a part of {len(part)} poses got {len(answer)} answers")
        for position, kept, item in zip(part.send.tolist(), part.keep.tolist(), answer, strict=True):
            if kept:
                out[position] = item
                filled[position] = True
    if not filled.all():
        raise ValueError(f"poses {np.flatnonzero(~filled).tolist()[:5]} got no answer")
    return [item for item in out if item is not None]


def lift_parts(
    count: int, parts: Sequence[Part], lift: Callable[[Part], Sequence[T]], done: Progress | None
) -> list[T]:
    """`lift` each part in turn (telling `done` how many poses each answered), assembled."""
    answers = []
    for part in parts:
        answers.append(lift(part))
        if done is not None:
            done(int(part.keep.sum()))
    return assemble(count, parts, answers)


def batches(count: int, size: int) -> list[Part]:
    """`count` poses in requests of at most `size`, in order (poses lifted alone need no context)."""
    return [
        Part(np.arange(a, min(a + size, count)), np.ones(min(size, count - a), bool))
        for a in range(0, count, size)
    ]
