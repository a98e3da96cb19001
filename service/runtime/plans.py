"""From single-frame answers to temporal ones: the windows of tracked poses (a stream's tracks, a
request's clips), the temporal model's run, and its answers held to the track's bone lengths."""

from __future__ import annotations

from collections.abc import Hashable, Sequence
from dataclasses import dataclass

import numpy as np

from repnet.core import geometry
from repnet.core.contract import Contract
from repnet.core.errors import InvalidKeypoints, LiftError, Violation
from repnet.core.inputs import ModelInput
from repnet.core.skeleton import BONES, bone_lengths, fix_bone_lengths
from repnet.runtime.lifter import Prediction
from repnet.runtime.replies import TemporalRows
from repnet.runtime.temporal import TemporalAnswer, TemporalBatcher, Windows, WindowSource, edge_padded
from repnet.runtime.tracks import Observation, TrackBudget, TrackTable, clip_windows, fps_violations


@dataclass(frozen=True)
class TemporalModels:
    """The loaded temporal models (one engine per mode present) and the bounds on their tracks."""

    engines: dict[str, TemporalBatcher]  # "causal", "offline"
    budget: TrackBudget  # every stream's tracks together
    per_stream: int  # most open tracks of one stream
    idle_s: float  # a track without a frame this long is dropped
    max_poses: int  # most poses of one temporal request

    def table(self) -> TrackTable | None:
        """A new stream's tracks (None without a causal model: its tracked poses are lifted alone)."""
        causal = self.engines.get("causal")
        if causal is None:
            return None
        return TrackTable(causal.lifter.contract, self.per_stream, self.idle_s, self.budget)


def camera_poses(prediction: Prediction, rows: np.ndarray, rotation: np.ndarray | None = None) -> np.ndarray:
    """(n, J, 3) the single-frame pose_3d of `rows` in the camera's orientation, without the ray turn:
    what the temporal model reads."""
    rotation = geometry.camera_rotation(prediction.camera[rows]) if rotation is None else rotation[rows]
    return geometry.rotate_to_camera(prediction.pose_3d[rows], rotation)


def seen_arrays(
    inputs: ModelInput, prediction: Prediction, rows: np.ndarray, rotation: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The single-frame answers of `rows` as a track stores them: (n, J, 3) poses, (n, J, 2)
    keypoints (0 where not visible) and (n, J) visibility, float32 (`rotation`: every row's
    camera_rotation, when the caller has it)."""
    poses = camera_poses(prediction, rows, rotation)
    points = np.where(inputs.visible[rows][..., None], inputs.keypoints_2d[rows], 0.0).astype(np.float32)
    return poses, points, inputs.visible[rows].astype(np.float32)


@dataclass(frozen=True)
class Plan:
    """What a temporal run needs: one window per answered row, the bone lengths to hold it to, and
    the rows that could not be tracked with why."""

    windows: WindowSource | None
    rows: np.ndarray  # (n,) rows of the request's inputs the windows answer, in window order
    bones: np.ndarray  # (n, B)
    errors: dict[int, LiftError]  # row -> why it gets no answer (its track's limit, its frame order)


@dataclass(frozen=True)
class TrackedRow:
    """A valid pose of a stream's frame that has a track."""

    row: int  # its row of the group's inputs
    track_id: str
    frame: int  # its frame number
    fps: float
    field: str  # what its errors are named: "pose", "people[2]"


def stream_plan(
    tracked: Sequence[tuple[TrackTable, TrackedRow]],
    inputs: ModelInput,
    prediction: Prediction,
    rotation: np.ndarray | None = None,
) -> Plan:
    """Push a batch's tracked poses into their streams' tracks, each stream's in the order it sent
    them, and take each one's causal window right after its push (the ring moves on). The rows are
    of `inputs`; each table is expired first; the answers' arrays and bone lengths are computed for
    all poses at once (`rotation`: every row's camera_rotation, if known). One temporal model's."""
    for table in {id(table): table for table, _ in tracked}.values():
        table.expire()
    rows = np.array([item.row for _, item in tracked], np.int64)
    poses, points, visibility = seen_arrays(inputs, prediction, rows, rotation)
    lengths = bone_lengths(poses)
    taken: list[int] = []
    slots: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    rates: list[float] = []
    bones: list[np.ndarray] = []
    errors: dict[int, LiftError] = {}
    for i, (table, item) in enumerate(tracked):
        try:
            track = table.get(item.track_id, item.fps, item.field)
        except InvalidKeypoints as err:  # the pose's answer
            errors[item.row] = err.as_answer()
            continue
        try:
            track.push(item.frame, Observation(poses[i], points[i], visibility[i]), lengths[i])
        except ValueError as err:
            reason = f"{err} (track {item.track_id!r})"
            errors[item.row] = InvalidKeypoints([Violation("frame_id", reason, "frame_order")])
            continue
        window_poses, window_points, window_seen, rate = track.window_slots(table.contract)
        slots.append((window_poses, window_points, window_seen))
        rates.append(rate)
        bones.append(track.bone_reference())
        taken.append(i)
    if not taken:
        return Plan(None, np.zeros(0, np.int64), np.zeros((0, len(BONES))), errors)
    longest = max(len(s[0]) for s in slots)
    slot_poses, slot_points, slot_seen = (
        np.stack([edge_padded(s[a], longest - len(s[a]), axis=0) for s in slots]) for a in range(3)
    )
    windows = Windows(slot_poses, slot_points, slot_seen, np.array(rates, np.float32))
    return Plan(windows, rows[taken], np.stack(bones), errors)


def clip_plan(
    rows: np.ndarray,
    track_ids: Sequence[str],
    frames: np.ndarray,
    fps: float,
    contract: Contract,
    inputs: ModelInput,
    prediction: Prediction,
) -> Plan:
    """The windows of a whole request's tracked poses (`rows` of its inputs, increasing, with their
    track and frame): causal, each from its track's frames up to it (as a stream answers them);
    offline, each from the frames around it in its track (bones: the mean of the segment). The
    contract's mode says which (tracks.clip_windows: built only when a batch runs)."""
    if not len(rows):
        return Plan(None, np.zeros(0, np.int64), np.zeros((0, len(BONES))), {})
    poses, points, visibility = seen_arrays(inputs, prediction, rows)
    windows, bones = clip_windows(track_ids, frames, fps, contract, poses, points, visibility)
    return Plan(windows, np.asarray(rows, np.int64), bones, {})


def answer_rows(plan: Plan, answer: TemporalAnswer) -> TemporalRows:
    """The temporal model's answers to the plan's windows, held to its bone lengths."""
    return TemporalRows(plan.rows, fix_bone_lengths(answer.pose_3d_camera, plan.bones), answer.failed)


async def run_plan(
    engine: TemporalBatcher, plan: Plan, transport: str, wait_s: float = 0.0, source: Hashable = None
) -> TemporalRows:
    """The temporal model's answers to the plan's windows (queued on `engine` for `source`), held to
    its bone lengths."""
    if plan.windows is None:
        return TemporalRows.none()
    return answer_rows(plan, await engine.lift_async(plan.windows, transport, wait_s, source))


def clip_violations(
    track_ids: Sequence[str | None], frames: Sequence[int | None], fps: float | None
) -> list[Violation]:
    """The rules of a clip of tracked poses (pose i: its track, None when untracked, and its frame
    number): the frame rate is given and in range, each tracked pose has a frame number, and no frame
    of a track comes twice. Fields are named within poses[i]."""
    found = fps_violations(fps, "fps")
    seen: dict[tuple[str, int], int] = {}
    for i, (track_id, frame) in enumerate(zip(track_ids, frames, strict=True)):
        if track_id is None:
            continue
        if frame is None:
            reason = "a tracked pose needs its frame number with temporal causal or offline"
            found.append(Violation("frame", reason, "frame_missing", pose=i).within(f"poses[{i}]"))
            continue
        first = seen.setdefault((track_id, frame), i)
        if first != i:
            reason = f"frame {frame} of this track is also poses[{first}]"
            found.append(Violation("frame", reason, "frame_repeated", pose=i).within(f"poses[{i}]"))
    return found
