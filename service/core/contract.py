"""A temporal model's contract: its window in time, causal or centred, and what it reads of a track
at a given frame rate (pure arithmetic, no onnxruntime: the clients use it too)."""

from __future__ import annotations

import math
from dataclasses import dataclass

MODES = ("causal", "offline")  # a temporal model's
TEMPORAL_MODES = ("off", *MODES)  # how a request lifts its tracked poses ("off": each alone)
MAX_GAP_S = 0.5  # the longest gap a track bridges; a longer one restarts it
MAX_FPS = 240.0  # the highest frame rate a track may declare
MAX_TRACK_ID = 128  # characters of a track id
DEFAULT_FPS = (
    30.0  # the frame rate clients assume for a sequence whose input gives none (OpenPose writes none)
)
ENVELOPE_BYTES = 1024  # what clients keep free of a body's byte limit besides its poses, with room to spare
# The largest frame number of a tracked pose: exact in a float64 (JavaScript's Number.MAX_SAFE_INTEGER),
# so every client and the page read it as sent, and frame arithmetic never overflows an int64.
MAX_FRAME = 2**53 - 1


def max_gap_frames(fps: float) -> int:
    """The most missing frames a track at `fps` bridges."""
    return int(round(MAX_GAP_S * fps))


def is_frame_number(value: object) -> bool:
    """`value` is a frame number: an integer (not a bool) from 0 to MAX_FRAME."""
    return isinstance(value, int) and not isinstance(value, bool) and 0 <= value <= MAX_FRAME


@dataclass(frozen=True)
class Contract:
    """What a temporal model's metadata promises (metadata entry `temporal`, JSON)."""

    mode: str  # causal | offline
    grid_fps: float  # the rate it resamples windows to
    window: int  # T grid frames it reads
    max_fps: float  # the highest slot rate it was trained for; faster tracks are thinned

    def thinning(self, fps: float) -> int:
        """q: a track at `fps` gives its window every q-th frame (at fps / q <= max_fps)."""
        return max(1, math.ceil(fps / self.max_fps - 1e-9))

    def slots(self, fps: float) -> int:
        """K: the frame slots of one window at slot rate `fps` (odd when offline)."""
        span = (self.window - 1) / self.grid_fps * fps
        if self.mode == "causal":
            return math.ceil(span - 1e-6) + 1
        return 2 * math.ceil(span / 2 - 1e-6) + 1

    def reach(self, fps: float) -> tuple[int, int]:
        """(before, after): how many frames before and after a frame its window reads, for a track
        at `fps` (tracks.Track.window, tracks.clip_windows): the context a part of a longer clip
        needs on each side to be answered as the whole clip would be."""
        q = self.thinning(fps)
        slots = self.slots(fps / q)
        if self.mode == "causal":
            return q * (slots - 1), 0
        return q * (slots // 2), q * (slots // 2)
