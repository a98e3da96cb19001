"""The temporal model: its onnxruntime session and contract, the windows it reads, the bone fix."""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import onnxruntime as ort

from repnet.core.contract import MODES, Contract
from repnet.core.errors import ModelLoadError
from repnet.core.formats import MODEL_JOINTS
from repnet.core.geometry import FloatArray
from repnet.runtime.batcher import Batcher
from repnet.runtime.lifter import model_id_of, non_finite_rows
from repnet.runtime.session import HasSessionOptions, open_session

log = logging.getLogger(__name__)

INPUTS = ("poses", "keypoints_2d", "visibility", "fps")
OUTPUT = "pose_3d_camera"
J = len(MODEL_JOINTS)
# The start-up check: a window of one pose repeated is answered within this of that pose (mean per
# joint, mm); a trained model moves it a few mm (its correction), a broken one anywhere.
STILL_TOLERANCE_MM = 100.0


@dataclass(frozen=True)
class Windows:
    """N windows of one track each: K frame slots evenly spaced in time around the answered frame
    (the last slot when causal, the middle one when offline)."""

    poses: FloatArray  # (N, K, J, 3) single-frame pose_3d_camera (no ray turn), mm, root at origin
    keypoints_2d: FloatArray  # (N, K, J, 2) px, 0 where not visible
    visibility: FloatArray  # (N, K, J) 0 or 1
    fps: FloatArray  # (N,) frames per second of the slots

    def __len__(self) -> int:
        return int(self.poses.shape[0])

    def slice(self, start: int, stop: int) -> Windows:
        """Windows start..stop-1 (views)."""
        return Windows(*(a[start:stop] for a in (self.poses, self.keypoints_2d, self.visibility, self.fps)))

    @classmethod
    def join(cls, parts: Sequence[Windows], causal: bool) -> Windows:
        """Windows of several requests as one batch: shorter windows get their end slots repeated
        (in front when causal, on both sides when offline), which changes no answer."""
        if len(parts) == 1:
            return parts[0]
        slots = max(p.poses.shape[1] for p in parts)
        padded = [pad_slots(p, slots, causal) for p in parts]
        arrays = zip(*((p.poses, p.keypoints_2d, p.visibility, p.fps) for p in padded), strict=True)
        return cls(*(np.concatenate(a) for a in arrays))

    def build(self) -> Windows:
        """These windows (already built)."""
        return self


@dataclass(frozen=True)
class ClipWindows:
    """N windows over the frames a request sent, built only when run (build): slot k of window i
    blends the sent frame at or before its time (`before`) with the next one (`after`), as a track
    bridges a gap (tracks.Track.push), so a request's windows cost 16 bytes a slot until a batch
    builds its own, whatever span of frames they cover."""

    poses: FloatArray  # (M, J, 3) the sent frames' single-frame pose_3d_camera (no ray turn), mm
    keypoints_2d: FloatArray  # (M, J, 2) px, 0 where not visible
    visibility: FloatArray  # (M, J) 0 or 1
    before: np.ndarray  # (N, K) int32: the sent frame at or before each slot's time
    after: np.ndarray  # (N, K) int32: the sent frame after it (`before` itself on a sent frame)
    weight: np.ndarray  # (N, K) float64: u, how far the slot lies from `before` to `after` (0 on one)
    fps: FloatArray  # (N,) frames per second of the slots

    def __len__(self) -> int:
        return int(self.before.shape[0])

    def slice(self, start: int, stop: int) -> ClipWindows:
        """Windows start..stop-1 (over the same sent frames)."""
        return replace(
            self,
            before=self.before[start:stop],
            after=self.after[start:stop],
            weight=self.weight[start:stop],
            fps=self.fps[start:stop],
        )

    def build(self) -> Windows:
        """The windows as the temporal model reads them: (1 - u) before + u after, seen where both
        are, each in float32 as Track.push computes it (the same answers to the bit)."""
        a, b, u = self.before, self.after, self.weight
        on_frame = (u == 0)[..., None]  # (N, K, 1)
        w0, w1 = (1.0 - u).astype(np.float32)[..., None], u.astype(np.float32)[..., None]
        seen = np.where(on_frame, self.visibility[a], np.minimum(self.visibility[a], self.visibility[b]))
        w0, w1 = w0[..., None], w1[..., None]  # (N, K, 1, 1)
        blend_k = (w0 * self.keypoints_2d[a] + w1 * self.keypoints_2d[b]) * seen[..., None]
        blend_p = w0 * self.poses[a] + w1 * self.poses[b]
        return Windows(
            np.where(on_frame[..., None], self.poses[a], blend_p),
            np.where(on_frame[..., None], self.keypoints_2d[a], blend_k),
            seen,
            self.fps,
        )


WindowSource = Windows | ClipWindows  # what a temporal batcher takes: windows built, or to build


def pad_slots(windows: Windows, slots: int, causal: bool) -> Windows:
    """The windows with `slots` slots: end slots repeated (offline: the same number each side)."""
    extra = slots - windows.poses.shape[1]
    if extra == 0:
        return windows
    before, after = (extra, 0) if causal else (extra // 2, extra - extra // 2)
    poses, points, seen = (
        edge_padded(a, before, after) for a in (windows.poses, windows.keypoints_2d, windows.visibility)
    )
    return Windows(poses, points, seen, windows.fps)


def edge_padded(slots: np.ndarray, before: int, after: int = 0, axis: int = 1) -> np.ndarray:
    """`slots` with its first slot along `axis` repeated `before` times in front and its last `after`
    times behind (a window's slots: axis 1 of a batch's, axis 0 of one window's)."""
    if before == after == 0:
        return slots
    widths = [(0, 0)] * slots.ndim
    widths[axis] = (before, after)
    return np.pad(slots, widths, mode="edge")


def read_contract(meta: dict[str, str], path: Path) -> Contract:
    """The `temporal` metadata entry, checked; ModelLoadError saying what is wrong."""
    if meta.get("kind") != "temporal":
        raise ModelLoadError(f"{path}: not a temporal model (metadata kind {meta.get('kind')!r})")
    try:
        raw = json.loads(meta["temporal"])
        mode, grid_fps, window, max_fps = raw["mode"], raw["grid_fps"], raw["window"], raw["max_fps"]
        contract = Contract(str(mode), float(grid_fps), int(window), float(max_fps))
    except (KeyError, ValueError, TypeError) as err:
        reason = f"metadata 'temporal' must give mode, grid_fps, window and max_fps ({err})"
        raise ModelLoadError(f"{path}: {reason}") from None
    if contract.mode not in MODES or contract.window < 1 or contract.grid_fps <= 0 or contract.max_fps <= 0:
        raise ModelLoadError(f"{path}: temporal contract {raw} is not a causal or offline window")
    if json.loads(meta.get("joint_names", "[]")) != list(MODEL_JOINTS):
        raise ModelLoadError(f"{path}: its joints are not the h36m17 joints the service lifts")
    return contract


class TemporalLifter:
    """Runs a temporal ONNX model (repnet.train.temporal.TemporalGraph); safe from many threads."""

    def __init__(self, session: ort.InferenceSession, path: Path) -> None:
        self.session = session
        self.path = path
        inputs = [i.name for i in session.get_inputs()]
        outputs = [o.name for o in session.get_outputs()]
        if inputs != list(INPUTS) or outputs != [OUTPUT]:
            raise ModelLoadError(
                f"{path}: a temporal model has inputs {list(INPUTS)} and output {OUTPUT}, "
                f"got {inputs} and {outputs}"
            )
        self.metadata = dict(session.get_modelmeta().custom_metadata_map)
        self.contract = read_contract(self.metadata, path)
        self.model_id = model_id_of(self.metadata, path)
        self.base_model_sha256 = self.metadata.get("base_model_sha256", "")

    @classmethod
    def load(cls, path: Path, settings: HasSessionOptions | None = None) -> TemporalLifter:
        """Open the temporal model at `path` (ModelLoadError saying what is wrong with it)."""
        lifter = cls(open_session(path, settings), path)
        log.info("loaded temporal model %s (%s) from %s", lifter.model_id, lifter.mode, path)
        return lifter

    @property
    def mode(self) -> str:
        """causal or offline."""
        return self.contract.mode

    @property
    def window(self) -> int:
        """T, grid frames in one window."""
        return self.contract.window

    def run(self, windows: Windows) -> TemporalAnswer:
        """The answered frame's pose_3d_camera of each window; non-finite rows marked failed."""
        feed = {
            "poses": windows.poses.astype(np.float32, copy=False),
            "keypoints_2d": windows.keypoints_2d.astype(np.float32, copy=False),
            "visibility": windows.visibility.astype(np.float32, copy=False),
            "fps": windows.fps.astype(np.float32, copy=False),
        }
        (pose,) = self.session.run([OUTPUT], feed)
        failed = non_finite_rows(pose)
        if failed.any():  # stand-ins, so that the other windows of the run are still answered
            pose = np.where(failed[:, None, None], 0.0, pose)
        return TemporalAnswer(pose.astype(np.float32, copy=False), failed)

    def check_outputs(self, poses: np.ndarray, keypoints_2d: np.ndarray, visibility: np.ndarray) -> None:
        """Answer windows of a person standing still at 25 and 60 fps: ModelLoadError unless the
        answers are finite and near the single-frame poses (a broken graph loads without complaint)."""
        for fps in (25.0, 60.0):
            slots = self.contract.slots(fps)
            p, k, v = (np.repeat(a[:, None], slots, axis=1) for a in (poses, keypoints_2d, visibility))
            answer = self.run(Windows(p, k, v, np.full(len(poses), fps, np.float32)))
            moved = np.linalg.norm(answer.pose_3d_camera - poses, axis=-1).mean(axis=1)  # (N,) mm
            if answer.failed.any() or not (moved < STILL_TOLERANCE_MM).all():
                raise ModelLoadError(
                    f"{self.path}: the temporal model fails its check at {fps:g} fps: a person standing "
                    f"still moved by {np.round(moved, 1).tolist()} mm (at most {STILL_TOLERANCE_MM:g})"
                )


@dataclass(frozen=True)
class TemporalAnswer:
    """What the temporal model answered for N windows."""

    pose_3d_camera: FloatArray  # (N, J, 3) mm, root at the origin, the camera's orientation (no ray)
    failed: np.ndarray  # (N,) not finite: a server fault for that pose

    def __len__(self) -> int:
        return int(self.failed.shape[0])

    def slice(self, start: int, stop: int) -> TemporalAnswer:
        """Answers start..stop-1 (views)."""
        return TemporalAnswer(self.pose_3d_camera[start:stop], self.failed[start:stop])

    @classmethod
    def join(cls, parts: Sequence[TemporalAnswer]) -> TemporalAnswer:
        """Answers of consecutive windows as one."""
        if len(parts) == 1:
            return parts[0]
        poses = np.concatenate([p.pose_3d_camera for p in parts])
        return cls(poses, np.concatenate([p.failed for p in parts]))


class TemporalBatcher(Batcher[WindowSource, TemporalAnswer]):
    """A temporal model's batcher: windows in (of any length: padded; ClipWindows built batch by
    batch on its thread, so a request's windows are never all built at once), TemporalAnswers out.
    Its runs are not in the single-frame metrics (inference_seconds, batch size)."""

    def __init__(
        self,
        lifter: TemporalLifter,
        *,
        max_batch: int,
        max_wait_s: float,
        queue_size: int,
        company_wait_s: float = 0.0,
    ) -> None:
        self.lifter = lifter
        super().__init__(
            None,
            max_batch=max_batch,
            max_wait_s=max_wait_s,
            queue_size=queue_size,
            name=f"{lifter.mode}-batcher",
            company_wait_s=company_wait_s,
        )

    def _run(self, parts: list[WindowSource]) -> TemporalAnswer:
        built = [p.build() for p in parts]
        return self.lifter.run(Windows.join(built, causal=self.lifter.mode == "causal"))

    def _join(self, parts: list[TemporalAnswer]) -> TemporalAnswer:
        return TemporalAnswer.join(parts)
