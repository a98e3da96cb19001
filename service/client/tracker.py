"""Tracks for files of detections: each person followed from frame to frame (a greedy tracker).

The rule, frame by frame in increasing order:
- the cost of a track for a pose of the next frame is the mean pixel distance between the track's
  last pose and the pose over the joints visible in both, divided by their body size (the mean of the
  two poses' spreads, geometry.visible_spread: the size the model normalises by);
- a pair is allowed when they share at least MIN_SHARED joints and its cost is at most
  GATE + GATE_PER_S * (the seconds since the track was last seen): a person moves further in a gap;
- allowed pairs are matched greedily, lowest cost first, each track and each pose at most once;
- a pose left over starts a new track;
- a track not seen for longer than the gap the service bridges (tracks.max_gap_frames at the clip's
  fps) has ended: whoever is seen there afterwards starts a new track, as the service would restart it.
Pure numpy; the page's static/track.js follows the same rule.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from repnet.core.contract import max_gap_frames
from repnet.core.geometry import visible_spread

MIN_SHARED = 4  # joints visible in both poses, for their distance to say anything
GATE = 0.5  # body sizes a person may move between consecutive frames and still be matched
GATE_PER_S = 2.0  # and more per second since the track was last seen


@dataclass
class _Track:
    """A track's last pose."""

    number: int
    frame: int
    points: np.ndarray  # (J, 2) px
    visible: np.ndarray  # (J,) bool
    size: float  # px, its spread


def costs(tracks: list[_Track], points: np.ndarray, visible: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    """(T, P) the cost of each track for each of P poses (points (P, J, 2), visible (P, J), sizes
    (P,)): mean shared-joint distance over the mean body size; inf with fewer than MIN_SHARED."""
    out = np.full((len(tracks), len(points)), np.inf)
    for t, track in enumerate(tracks):
        shared = visible & track.visible[None]  # (P, J)
        count = shared.sum(axis=1)  # (P,)
        gaps = np.linalg.norm(np.where(shared[..., None], points - track.points, 0.0), axis=-1)  # (P, J)
        mean = gaps.sum(axis=1) / np.maximum(count, 1)
        scale = (sizes + track.size) / 2
        ok = (count >= MIN_SHARED) & (scale > 0)
        out[t, ok] = mean[ok] / scale[ok]
    return out


def match(cost: np.ndarray, allowed: np.ndarray) -> list[tuple[int, int]]:
    """Greedy matching: (row, column) pairs of `allowed` cells, lowest cost first, each row and
    column at most once (ties: the lower row, then the lower column)."""
    rows, cols = np.nonzero(allowed)
    order = np.lexsort((cols, rows, cost[rows, cols]))
    used_rows: set[int] = set()
    used_cols: set[int] = set()
    pairs = []
    for r, c in zip(rows[order].tolist(), cols[order].tolist(), strict=True):
        if r not in used_rows and c not in used_cols:
            pairs.append((r, c))
            used_rows.add(r)
            used_cols.add(c)
    return pairs


def assign_tracks(frames: np.ndarray, points: np.ndarray, fps: float) -> np.ndarray:
    """(N,) the track number of each of N poses (0, 1, ... in order of appearance).

    frames -- (N,) int frame number of each pose (several poses per frame: several people);
    points -- (N, J, 2) px, NaN where a joint is missing; fps -- the frame rate of the numbers."""
    frames = np.asarray(frames, dtype=np.int64)
    visible = ~np.isnan(points).any(axis=-1)  # (N, J)
    clean = np.where(visible[..., None], points, 0.0)
    sizes = visible_spread(clean, visible)  # (N,) px
    out = np.full(len(frames), -1, np.int64)
    tracks: list[_Track] = []
    longest_gap = max_gap_frames(fps)
    made = 0
    for frame in np.unique(frames).tolist():
        here = np.flatnonzero(frames == frame)
        tracks = [t for t in tracks if frame - t.frame - 1 <= longest_gap]
        cost = costs(tracks, clean[here], visible[here], sizes[here])
        since_s = np.array([(frame - t.frame) / fps for t in tracks]).reshape(-1, 1)
        pairs = match(cost, cost <= GATE + GATE_PER_S * since_s)
        taken = {c: tracks[r] for r, c in pairs}
        for k, pose in enumerate(here.tolist()):
            track = taken.get(k)
            if track is None:
                track = _Track(made, frame, clean[pose], visible[pose], float(sizes[pose]))
                tracks.append(track)
                made += 1
            track.frame, track.points, track.visible = frame, clean[pose], visible[pose]
            track.size = float(sizes[pose])
            out[pose] = track.number
    return out
