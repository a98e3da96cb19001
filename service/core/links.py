"""Which poses of an input are consecutive frames of one person: per pose, the row of the same
person's pose in the frame before it (-1 where there is none). `repnet adapt` judges the smoothness
of its answers along these links (repnet.train.adapt)."""

from __future__ import annotations

from collections.abc import Hashable, Sequence

import numpy as np
import numpy.typing as npt

Links = npt.NDArray[np.int64]


def previous_frames(frames: npt.ArrayLike, people: Sequence[Hashable | None]) -> Links:
    """(N,) per pose the row of the pose of the same person (`people`, None: unknown) in frame
    `frames`[i] - 1, -1 where there is none."""
    frame = np.asarray(frames, dtype=np.int64)
    pairs = list(zip(people, frame.tolist(), strict=True))
    row_of = {(who, f): i for i, (who, f) in enumerate(pairs) if who is not None}
    return np.array([-1 if who is None else row_of.get((who, f - 1), -1) for who, f in pairs], dtype=np.int64)


def kept_links(previous: Links, kept: npt.NDArray[np.bool_]) -> Links:
    """`previous` (N,) of all rows -> that of the rows where `kept` (N,) is True, renumbered among
    them; a row whose frame before was not kept gets -1."""
    number = np.cumsum(kept) - 1
    mine = previous[kept]
    before = np.maximum(mine, 0)
    return np.where((mine >= 0) & kept[before], number[before], -1).astype(np.int64)


def shifted(previous: Links, by: int) -> Links:
    """`previous` of one input as rows of a list that starts `by` rows before it."""
    return np.where(previous >= 0, previous + by, -1).astype(np.int64)
