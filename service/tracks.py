"""Tracks: one person's frames in time, bounded, and the temporal model's windows over them.

A track holds the single-frame answers (pose_3d_camera without the ray turn, the model-joint
keypoints and their visibility) of its recent frames in a ring buffer, numbered by frame. Frames
must come in increasing order. A gap of at most MAX_GAP_S is bridged: the missing frames are
filled by linear interpolation between the frames on either side, so the window stays evenly
spaced in time; a longer gap restarts the track (its window and bone lengths start again).

A causal window (Track.window) holds the newest frame and the K - 1 before it, the oldest
repeated while the track is younger than that; an offline window (offline_windows) is centred on
its frame over a whole clip, the clip's ends repeated. A track faster than the model's max_fps
gives every q-th frame (contract.Contract.thinning). Its bone lengths are the running mean of the
single-frame answers' (temporal.fix_bone_lengths holds the temporal answer to them).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from service.contract import Contract
from service.errors import InvalidKeypoints, Violation
from service.temporal import BONES, J, Windows, bone_lengths

MAX_GAP_S = 0.5  # the longest gap a track bridges; a longer one restarts it
MAX_FPS = 240.0  # the highest frame rate a track may declare
MAX_TRACK_ID = 128  # characters of a track id


def max_gap_frames(fps: float) -> int:
    """The most missing frames a track at `fps` bridges."""
    return int(round(MAX_GAP_S * fps))


def fps_violations(fps: float | None, field: str) -> list[Violation]:
    """A track's frame rate must be given, finite and in (0, MAX_FPS]."""
    if fps is None:
        return [Violation(field, "tracked poses need the frame rate: give fps", "fps_missing")]
    if not (np.isfinite(fps) and 0 < fps <= MAX_FPS):
        return [Violation(field, f"must be a number in (0, {MAX_FPS:g}], got {fps:g}", "fps_range")]
    return []


@dataclass(frozen=True)
class Observation:
    """One frame of one person, as the single-frame model answered it."""

    pose: np.ndarray  # (J, 3) pose_3d_camera without the ray turn, mm, root at origin
    keypoints: np.ndarray  # (J, 2) model-joint px, 0 where not visible
    visibility: np.ndarray  # (J,) 0 or 1


class Track:
    """One person's recent frames (a ring buffer of `capacity`), their running bone lengths."""

    def __init__(self, capacity: int, fps: float) -> None:
        self.capacity = capacity
        self.fps = fps
        self.poses = np.zeros((capacity, J, 3), np.float32)
        self.keypoints = np.zeros((capacity, J, 2), np.float32)
        self.visibility = np.zeros((capacity, J), np.float32)
        self.stored = 0  # frames stored since the track (re)started, bridged ones included
        self.last_frame = -1
        self.last_seen = time.monotonic()
        self.bone_sum = np.zeros(len(BONES))
        self.bone_count = 0

    @property
    def nbytes(self) -> int:
        """Bytes of state this track holds."""
        return track_bytes(self.capacity)

    def _store(self, pose: np.ndarray, keypoints: np.ndarray, visibility: np.ndarray) -> None:
        slot = self.stored % self.capacity
        self.poses[slot], self.keypoints[slot], self.visibility[slot] = pose, keypoints, visibility
        self.stored += 1

    def push(self, frame: int, seen: Observation) -> None:
        """Add frame number `frame` (larger than the last): bridge a short gap, restart after a long one."""
        if self.stored and frame <= self.last_frame:
            raise ValueError(f"frame {frame} comes after frame {self.last_frame} of its track")
        gap = frame - self.last_frame - 1
        if not self.stored or gap > max_gap_frames(self.fps):
            self.stored, self.bone_sum[:], self.bone_count = 0, 0.0, 0
        elif gap > 0:
            last = (self.stored - 1) % self.capacity
            before = (self.poses[last], self.keypoints[last], self.visibility[last])
            for k in range(1, gap + 1):
                u = k / (gap + 1)
                seen_both = np.minimum(before[2], seen.visibility)
                points = ((1 - u) * before[1] + u * seen.keypoints) * seen_both[:, None]
                self._store((1 - u) * before[0] + u * seen.pose, points, seen_both)
        self._store(seen.pose, seen.keypoints, seen.visibility)
        self.bone_sum += bone_lengths(seen.pose[None])[0]
        self.bone_count += 1
        self.last_frame = frame
        self.last_seen = time.monotonic()

    def window(self, contract: Contract) -> Windows:
        """The causal window of the newest frame (one window, N = 1)."""
        q = contract.thinning(self.fps)
        slots = contract.slots(self.fps / q)
        newest = self.stored - 1
        back = np.maximum(newest - q * np.arange(slots - 1, -1, -1), max(0, self.stored - self.capacity))
        index = back % self.capacity
        return Windows(
            self.poses[index][None],
            self.keypoints[index][None],
            self.visibility[index][None],
            np.array([self.fps / q], np.float32),
        )

    def bone_reference(self) -> np.ndarray:
        """(B,) the mean bone lengths of the single-frame answers since the track (re)started."""
        return self.bone_sum / max(self.bone_count, 1)


def track_capacity(contract: Contract, fps: float) -> int:
    """Frames a track at `fps` must keep for its causal window: the newest frame and the q (K - 1)
    before it (K slots, every q-th frame). A track's rate never changes (a new rate restarts it), so
    its ring is sized for its own rate (49 frames at 30 fps, 385 at 240 with the bundled model)."""
    q = contract.thinning(fps)
    return q * (contract.slots(fps / q) - 1) + 1


def track_bytes(capacity: int) -> int:
    """The bytes one track of `capacity` frames holds (Track.nbytes)."""
    return 4 * capacity * J * (3 + 2 + 1) + 8 * len(BONES)


class TrackLimitReached(InvalidKeypoints):
    """A new track would pass the stream's or the server's limit on open tracks."""


class TrackTable:
    """The open tracks of one stream: at most `per_stream`, and together with every other stream's
    at most what `budget` allows; a track not seen for `idle_s` is dropped."""

    def __init__(self, contract: Contract, per_stream: int, idle_s: float, budget: TrackBudget) -> None:
        self.contract = contract
        self.per_stream = per_stream
        self.idle_s = idle_s
        self.budget = budget
        self.tracks: dict[str, Track] = {}

    def expire(self, now: float | None = None) -> int:
        """Drop the tracks not seen for idle_s; returns how many."""
        now = time.monotonic() if now is None else now
        stale = [key for key, track in self.tracks.items() if now - track.last_seen > self.idle_s]
        for key in stale:
            self._drop(key)
        return len(stale)

    def get(self, track_id: str, fps: float, field: str) -> Track:
        """The track `track_id` (a track whose frame rate changes starts again); a new one within the
        limits, else TrackLimitReached naming `field`."""
        track = self.tracks.get(track_id)
        if track is not None and track.fps == fps:
            return track
        if track is not None:
            self._drop(track_id)
        if len(self.tracks) >= self.per_stream:
            reason = f"a stream holds at most {self.per_stream} open tracks (REPNET_STREAM_MAX_TRACKS)"
            raise TrackLimitReached([Violation(field, reason, "too_many_tracks")])
        capacity = track_capacity(self.contract, fps)
        if not self.budget.take(track_bytes(capacity)):
            limit = self.budget.limit
            reason = f"the server holds at most {limit} open tracks (REPNET_MAX_TRACKS); retry later"
            raise TrackLimitReached([Violation(field, reason, "too_many_tracks")])
        track = self.tracks[track_id] = Track(capacity, fps)
        return track

    def _drop(self, track_id: str) -> None:
        track = self.tracks.pop(track_id)
        self.budget.give(track.nbytes)

    def close(self) -> None:
        """Free every track (the stream ended)."""
        for key in list(self.tracks):
            self._drop(key)


class TrackBudget:
    """The server's open tracks, over all streams, and the bytes they hold; `on_change(tracks,
    bytes)` is told each change (the gauges). Used from the gRPC server's one event loop."""

    def __init__(self, limit: int, on_change: Callable[[int, int], None] | None = None) -> None:
        self.limit = limit
        self.open = 0
        self.bytes = 0
        self.on_change = on_change

    def take(self, nbytes: int) -> bool:
        """Count one more track holding `nbytes`; False at the limit."""
        if self.open >= self.limit:
            return False
        self.open += 1
        self.bytes += nbytes
        self._changed()
        return True

    def give(self, nbytes: int) -> None:
        """A track holding `nbytes` was freed."""
        self.open -= 1
        self.bytes -= nbytes
        self._changed()

    def _changed(self) -> None:
        if self.on_change is not None:
            self.on_change(self.open, self.bytes)


def segments(frames: np.ndarray, fps: float) -> list[np.ndarray]:
    """Positions of one track's increasing frame numbers, split where a gap is too long to bridge."""
    cut = np.flatnonzero(np.diff(frames) - 1 > max_gap_frames(fps)) + 1
    return np.split(np.arange(len(frames)), cut)


def bridged_clip(
    frames: np.ndarray, seen: list[Observation], fps: float
) -> tuple[Windows, np.ndarray, np.ndarray]:
    """One segment of a track as one evenly spaced clip (short gaps bridged as Track.push bridges
    them): the clip (N = 1), where each given frame sits in it, and the mean bone lengths."""
    span = int(frames[-1] - frames[0]) + 1
    track = Track(span, fps)
    where = np.empty(len(frames), np.int64)
    for k, (frame, observation) in enumerate(zip(frames.tolist(), seen, strict=True)):
        track.push(frame, observation)
        where[k] = track.stored - 1
    n = track.stored
    clip = Windows(
        track.poses[None, :n],
        track.keypoints[None, :n],
        track.visibility[None, :n],
        np.array([fps], np.float32),
    )
    return clip, where, track.bone_reference()


def offline_windows(clip: Windows, contract: Contract) -> Windows:
    """The offline window of every frame of one clip (N = 1 in, one window per frame out): frames
    centred on it, the clip's ends repeated."""
    frames = clip.poses.shape[1]
    fps = float(clip.fps[0])
    q = contract.thinning(fps)
    half = contract.slots(fps / q) // 2
    index = np.clip(np.arange(frames)[:, None] + q * np.arange(-half, half + 1)[None], 0, frames - 1)
    return Windows(
        clip.poses[0][index],
        clip.keypoints_2d[0][index],
        clip.visibility[0][index],
        np.full(frames, fps / q, np.float32),
    )
