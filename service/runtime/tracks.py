"""Tracks: one person's frames in time, bounded, and the temporal model's windows over them.

A track holds the single-frame answers (pose_3d_camera without the ray turn, the model-joint
keypoints and their visibility) of its recent frames in a ring buffer, numbered by frame. Frames
must come in increasing order. A gap of at most MAX_GAP_S is bridged: the missing frames are
filled by linear interpolation between the frames on either side, so the window stays evenly
spaced in time; a longer gap restarts the track (its window and bone lengths start again).

A causal window (Track.window) holds the newest frame and the K - 1 before it, the oldest
repeated while the track is younger than that; an offline window (clip_windows) is centred on
its frame over a whole clip, the clip's ends repeated. A track faster than the model's max_fps
gives every q-th frame (contract.Contract.thinning). Its bone lengths are the running mean of the
single-frame answers' (temporal.fix_bone_lengths holds the temporal answer to them).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from repnet.core.contract import MAX_FPS, Contract, max_gap_frames
from repnet.core.errors import InvalidKeypoints, Violation
from repnet.core.skeleton import BONES, bone_lengths
from repnet.runtime.temporal import ClipWindows, J, Windows


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

    def push(self, frame: int, seen: Observation, lengths: np.ndarray | None = None) -> None:
        """Add frame number `frame` (larger than the last): bridge a short gap, restart after a long one.
        `lengths`: the (B,) bone lengths of seen.pose, when the caller has them (a batch's at once)."""
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
        self.bone_sum += bone_lengths(seen.pose[None])[0] if lengths is None else lengths
        self.bone_count += 1
        self.last_frame = frame
        self.last_seen = time.monotonic()

    def window(self, contract: Contract) -> Windows:
        """The causal window of the newest frame (one window, N = 1)."""
        poses, keypoints, visibility, rate = self.window_slots(contract)
        return Windows(poses[None], keypoints[None], visibility[None], np.array([rate], np.float32))

    def window_slots(self, contract: Contract) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """The causal window of the newest frame as its (K, J, 3) poses, (K, J, 2) keypoints and (K, J)
        visibility (copies: the ring moves on), and the rate of its slots: the newest frame and every
        q-th before it (contract.thinning), the oldest repeated while the track is younger than the
        window."""
        q = contract.thinning(self.fps)
        newest = self.stored - 1
        back = np.maximum(
            newest - q * np.arange(contract.slots(self.fps / q) - 1, -1, -1),
            max(0, self.stored - self.capacity),
        )
        index = back % self.capacity
        return self.poses[index], self.keypoints[index], self.visibility[index], self.fps / q

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
    at most what `budget` allows; a track not seen for `idle_s` is dropped. Its stream's event loop
    expires and closes it while the batcher's thread pushes frames into it: a lock keeps the two
    apart, and a closed table opens no track (its budget is given back once)."""

    def __init__(self, contract: Contract, per_stream: int, idle_s: float, budget: TrackBudget) -> None:
        self.contract = contract
        self.per_stream = per_stream
        self.idle_s = idle_s
        self.budget = budget
        self.tracks: dict[str, Track] = {}
        self.closed = False
        self._lock = threading.Lock()

    def expire(self, now: float | None = None) -> int:
        """Drop the tracks not seen for idle_s; returns how many."""
        now = time.monotonic() if now is None else now
        with self._lock:
            stale = [key for key, track in self.tracks.items() if now - track.last_seen > self.idle_s]
            for key in stale:
                self._drop(key)
        return len(stale)

    def get(self, track_id: str, fps: float, field: str) -> Track:
        """The track `track_id` (a track whose frame rate changes starts again); a new one within the
        limits, else TrackLimitReached naming `field`."""
        with self._lock:
            return self._get(track_id, fps, field)

    def _get(self, track_id: str, fps: float, field: str) -> Track:
        if self.closed:
            raise TrackLimitReached([Violation(field, "the stream has ended", "stream_closed")])
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
            budget = self.budget
            reason = (
                f"the server holds at most {budget.limit} open tracks (REPNET_MAX_TRACKS) and "
                f"{budget.max_bytes} bytes of track state (REPNET_TRACK_MEMORY_MB); retry later"
            )
            raise TrackLimitReached([Violation(field, reason, "too_many_tracks")])
        track = self.tracks[track_id] = Track(capacity, fps)
        return track

    def _drop(self, track_id: str) -> None:
        track = self.tracks.pop(track_id)
        self.budget.give(track.nbytes)

    def close(self) -> None:
        """Free every track (the stream ended)."""
        with self._lock:
            self.closed = True
            for key in list(self.tracks):
                self._drop(key)


class TrackBudget:
    """The server's open tracks, over all streams, and the bytes they hold; `on_change(tracks,
    bytes)` is told each change (the gauges). Streams of every model's batcher share it: a lock."""

    def __init__(
        self, limit: int, on_change: Callable[[int, int], None] | None = None, max_bytes: int | None = None
    ) -> None:
        self.limit = limit
        self.max_bytes = max_bytes  # the most the open tracks hold together (None: no bound but limit)
        self.open = 0
        self.bytes = 0
        self.on_change = on_change
        self._lock = threading.Lock()

    def take(self, nbytes: int) -> bool:
        """Count one more track holding `nbytes`; False at the limit on tracks or on their bytes."""
        with self._lock:
            over_bytes = self.max_bytes is not None and self.bytes + nbytes > self.max_bytes
            if self.open >= self.limit or over_bytes:
                return False
            self.open += 1
            self.bytes += nbytes
            self._changed()
        return True

    def give(self, nbytes: int) -> None:
        """A track holding `nbytes` was freed."""
        with self._lock:
            self.open -= 1
            self.bytes -= nbytes
            self._changed()

    def _changed(self) -> None:
        if self.on_change is not None:
            self.on_change(self.open, self.bytes)


def clip_windows(
    track_ids: Sequence[str],
    frames: np.ndarray,
    fps: float,
    contract: Contract,
    poses: np.ndarray,
    keypoints: np.ndarray,
    visibility: np.ndarray,
) -> tuple[ClipWindows, np.ndarray]:
    """The window of each of a request's tracked poses (M of them: `track_ids`, `frames` (M,) and
    their single-frame answers as a Track stores them, (M, J, 3), (M, J, 2), (M, J)), in their order,
    and (M, B) the bone lengths to hold each answer to.

    A track's poses are taken in frame order and split where a gap is too long to bridge (segments);
    within a segment, a window reads the frames before it (causal: as Track.window reads them after
    the same pushes) or around it (offline: the segment's ends repeated), shorter gaps bridged as
    Track.push bridges them. Bones: causal, the mean of the segment's answers up to the pose;
    offline, of the whole segment. Nothing of the frames between the sent ones is built
    (ClipWindows): the cost is M poses and M x K slot indexes, whatever span the frames cover.
    """
    count = len(frames)
    q = contract.thinning(fps)
    slots = contract.slots(fps / q)
    causal = contract.mode == "causal"
    offsets = q * (np.arange(slots) - (slots - 1 if causal else slots // 2))  # (K,) frames from the pose
    codes: dict[str, int] = {}
    track = np.array([codes.setdefault(t, len(codes)) for t in track_ids], np.int64)
    frames = np.asarray(frames, np.int64)
    order = np.lexsort((frames, track))  # by track, then frame (stable)
    sorted_frames = frames[order]
    cut = (np.diff(track[order]) != 0) | (np.diff(sorted_frames) - 1 > max_gap_frames(fps))
    starts = np.flatnonzero(np.concatenate([[True], cut]))  # each segment's first position in `order`
    ends = np.append(starts[1:], count) - 1
    segment = np.cumsum(np.concatenate([[False], cut]))  # (M,) segment of each sorted pose
    # One increasing time line over all segments: a segment's frames from its first, then the next
    # segment after its last (a segment spans at most M gaps of max_gap_frames, so no overflow).
    span = sorted_frames[ends] - sorted_frames[starts] + 1
    base = np.concatenate([[0], np.cumsum(span)[:-1]])
    line = sorted_frames - sorted_frames[starts][segment] + base[segment]  # (M,) increasing
    first, last = line[starts][segment], line[ends][segment]  # (M,) the segment's ends on the line
    wanted = np.clip(line[:, None] + offsets[None], first[:, None], last[:, None])  # (M, K)
    at = np.searchsorted(line, wanted, side="right") - 1  # the sent frame at or before each slot
    on_frame = line[at] == wanted
    nxt = np.where(on_frame, at, np.minimum(at + 1, count - 1))
    gap = np.where(on_frame, 1, line[nxt] - line[at])
    weight = np.where(on_frame, 0.0, (wanted - line[at]) / gap)
    lengths = bone_lengths(poses[order]).astype(np.float64)  # (M, B), summed as Track sums them
    bones = np.empty_like(lengths)
    for a, b in zip(starts.tolist(), ends.tolist(), strict=True):
        running = np.cumsum(lengths[a : b + 1], axis=0)
        count_so_far = np.arange(1, b - a + 2)[:, None]
        bones[a : b + 1] = running / count_so_far if causal else running[-1] / (b - a + 1)
    back = np.empty(count, np.int64)
    back[order] = np.arange(count)  # sorted position of each pose
    windows = ClipWindows(
        poses,
        keypoints,
        visibility,
        order[at[back]].astype(np.int32),  # M <= max_temporal_poses
        order[nxt[back]].astype(np.int32),
        weight[back],
        np.full(count, fps / q, np.float32),
    )
    return windows, bones[back]
