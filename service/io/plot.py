"""Figures of lifted poses: the 2D input with its reprojection, and the 3D pose from two viewpoints."""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from repnet.core.formats import FORMATS, MODEL_JOINTS, MODEL_PARENTS, to_model_joints

LEFT, RIGHT, CENTRE = "#1f77b4", "#d62728", "#444444"  # the subject's left blue, right red


def side_colour(joint: str) -> str:
    """The colour of a joint by its side of the body."""
    return LEFT if joint.startswith("left_") else RIGHT if joint.startswith("right_") else CENTRE


def _bones(parents: tuple[int, ...]) -> list[tuple[int, int]]:
    """(parent, child) pairs; a bone takes the colour of its child's side."""
    return [(p, c) for c, p in enumerate(parents) if p >= 0]


def _draw_2d(ax: Any, points: np.ndarray, visible: np.ndarray, **style: Any) -> None:
    """Bones of the (17, 2) skeleton between visible joints, coloured by side (one line per bone,
    empty where a joint is not visible, so that an animation can move every bone)."""
    for p, c in _bones(MODEL_PARENTS):
        x, y = _bone_2d(points, visible, p, c)
        ax.plot(x, y, color=side_colour(MODEL_JOINTS[c]), **style)


def _bone_2d(points: np.ndarray, visible: np.ndarray, p: int, c: int) -> tuple[np.ndarray, np.ndarray]:
    """The x and y of bone p-c, NaN (not drawn) unless both joints are visible."""
    if visible[p] and visible[c]:
        return points[[p, c], 0], points[[p, c], 1]
    return np.full(2, np.nan), np.full(2, np.nan)


Box = tuple[np.ndarray, float]  # a square window: centre and half its side


def _square(points: np.ndarray, margin: float, pad: float) -> Box:
    """The window around (M, D) points: centred on their extent, half the largest side + pad."""
    centre = (points.max(axis=0) + points.min(axis=0)) / 2
    return centre, float(np.ptp(points, axis=0).max()) * margin + pad


def _view_3d(pose: np.ndarray) -> np.ndarray:
    """(17, 3) camera-like pose (x right, y down, z depth) -> (17, 3) plotted x, depth, up."""
    return np.stack([pose[:, 0], pose[:, 2], -pose[:, 1]], axis=1)


def _draw_3d(
    ax: Any,
    pose: np.ndarray,
    imputed: np.ndarray,
    title: str,
    elev: float,
    azim: float,
    box: Box | None = None,
) -> None:
    """(17, 3) pose in a camera-like frame (x right, y down, z depth) shown with up pointing up,
    in `box` (default: around the pose itself)."""
    view = _view_3d(pose)
    x, depth, up = view[:, 0], view[:, 1], view[:, 2]
    for p, c in _bones(MODEL_PARENTS):
        ax.plot(x[[p, c]], depth[[p, c]], up[[p, c]], color=side_colour(MODEL_JOINTS[c]), linewidth=2.5)
    colours = [side_colour(j) for j in MODEL_JOINTS]
    ax.scatter(x, depth, up, c=colours, s=14, depthshade=False)
    ax.scatter(x[imputed], depth[imputed], up[imputed], facecolors="none", edgecolors="k", s=60)
    centre, half = box or (view.mean(axis=0), max(np.ptp(x), np.ptp(depth), np.ptp(up)) / 2 + 50)
    ax.set_xlim(centre[0] - half, centre[0] + half)
    ax.set_ylim(centre[1] - half, centre[1] + half)
    ax.set_zlim(centre[2] - half, centre[2] + half)
    ax.set_box_aspect((1, 1, 1))
    ax.locator_params(nbins=5)
    ax.tick_params(labelsize=7)
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("depth (mm)")
    ax.set_zlabel("up (mm)")
    ax.view_init(elev=elev, azim=azim)
    ax.set_title(title)


def _figure() -> tuple[Any, tuple[Any, Any, Any]]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(16, 5.5), layout="constrained")
    axes = (
        fig.add_subplot(1, 3, 1),
        fig.add_subplot(1, 3, 2, projection="3d"),
        fig.add_subplot(1, 3, 3, projection="3d"),
    )
    return fig, axes


def _draw(
    axes: tuple[Any, Any, Any],
    fmt_name: str,
    keypoints: np.ndarray,
    pose: dict[str, Any],
    window: Box | None = None,
    box: Box | None = None,
) -> None:
    """One lifted pose on the three panels; `window` and `box` fix the 2D and 3D views (sequences)."""
    from matplotlib.lines import Line2D

    fmt = FORMATS[fmt_name]
    present = ~np.isnan(keypoints).any(axis=1)
    model_points, model_visible, _, _ = to_model_joints(fmt, keypoints[None], present[None])
    reprojection = np.asarray(pose["reprojection"], dtype=np.float64)  # (17, 2)
    imputed = np.asarray(pose["imputed"], dtype=bool)
    ax = axes[0]
    ax.scatter(keypoints[present, 0], keypoints[present, 1], s=10, color="0.6", label="detector joints")
    _draw_2d(ax, model_points[0], model_visible[0], linewidth=2.5)
    _draw_2d(ax, reprojection, np.ones(17, bool), linewidth=1.2, linestyle="--")
    ax.scatter(reprojection[imputed, 0], reprojection[imputed, 1], marker="x", color="k", s=40)
    centre, half = window or _square(np.concatenate([keypoints[present], reprojection]), 0.6, 1)
    ax.set_xlim(centre[0] - half, centre[0] + half)
    ax.set_ylim(centre[1] + half, centre[1] - half)  # image y points down
    ax.set_aspect("equal")
    ax.set_xlabel("x (px)")
    ax.set_ylabel("y (px)")
    ax.set_title(f"2D input ({fmt_name}) and reprojection\nerror {pose['reprojection_error_px']:.1f} px")
    ax.legend(
        handles=[
            Line2D([], [], color=CENTRE, linewidth=2.5, label="input"),
            Line2D([], [], color=CENTRE, linewidth=1.2, linestyle="--", label="reprojection"),
            Line2D([], [], color=LEFT, label="left"),
            Line2D([], [], color=RIGHT, label="right"),
            Line2D([], [], marker="x", color="k", linestyle="", label="imputed"),
        ],
        loc="lower left",
        fontsize="small",
        framealpha=0.6,
    )
    pose_camera = np.asarray(pose["pose_3d_camera"], dtype=np.float64)  # (17, 3)
    _draw_3d(axes[1], pose_camera, imputed, "3D, seen from the camera", 10, -90, box)
    _draw_3d(axes[2], pose_camera, imputed, "3D, seen from the side", 10, 0, box)


def plot_pose(
    output: Path, fmt_name: str, keypoints: np.ndarray, pose: dict[str, Any], model_id: str
) -> None:
    """Write a figure of one lifted pose: `keypoints` (K, 2) in `fmt_name`, NaN where missing;
    `pose` the reply's fields (pose_3d_camera, reprojection, imputed, reprojection_error_px)."""
    import matplotlib.pyplot as plt

    fig, axes = _figure()
    _draw(axes, fmt_name, keypoints, pose)
    fig.suptitle(f"RepNet lift, model {model_id}")
    fig.savefig(output, dpi=100)
    plt.close(fig)


def _writer(output: Path, fps: int) -> Any:
    """The matplotlib writer of an MP4 (ffmpeg); None for a GIF (blitted, written by Pillow)."""
    from matplotlib import animation

    if output.suffix == ".gif":
        return None
    if not animation.writers.is_available("ffmpeg"):
        raise ValueError(f"{output}: writing .mp4 needs ffmpeg on the PATH; write a .gif instead")
    return animation.FFMpegWriter(fps=fps)


def animate_poses(
    output: Path,
    fmt_name: str,
    frames: Sequence[tuple[np.ndarray, dict[str, Any], str]],
    model_id: str,
    fps: int = 10,
    progress: Callable[[int, int], None] | None = None,
) -> None:
    """Write an animation (.gif, or .mp4 with ffmpeg) of lifted poses, one per frame: each item is
    (keypoints (K, 2) NaN where missing, the reply's fields, a caption). The views stay fixed.

    The first frame is drawn in full (axes, ticks, legend, layout) once; each frame then only moves
    the data of the pose's artists. A GIF blits: the still background is copied back and only the
    moving artists are drawn on it, and Pillow writes the frames (bench.plot_speed: 60 frames in a
    few seconds instead of 27 s when every frame redrew the axes)."""
    import matplotlib.pyplot as plt

    writer = _writer(output, fps)
    shown = np.concatenate(
        [np.concatenate([k[~np.isnan(k).any(axis=1)], np.asarray(p["reprojection"])]) for k, p, _ in frames]
    )
    window = _square(shown, 0.6, 1)
    views = np.concatenate([_view_3d(np.asarray(p["pose_3d_camera"], float)) for _, p, _ in frames])
    box = _square(views, 0.5, 50)
    fig, axes = _figure()
    fig.set_dpi(ANIMATION_DPI)
    keypoints, pose, caption = frames[0]
    _draw(axes, fmt_name, keypoints, pose, window, box)
    title = fig.suptitle(f"RepNet lift, model {model_id}: {caption}")
    fig.canvas.draw()  # the constrained layout, once: later frames keep it
    fig.set_layout_engine("none")
    movers = [_Movers(ax) for ax in axes]
    fmt = FORMATS[fmt_name]

    def move(i: int) -> None:
        keypoints, pose, caption = frames[i]
        present = ~np.isnan(keypoints).any(axis=1)
        model_points, model_visible, _, _ = to_model_joints(fmt, keypoints[None], present[None])
        movers[0].move_2d(keypoints[present], model_points[0], model_visible[0], pose)
        view, imputed = _view_3d(np.asarray(pose["pose_3d_camera"], float)), np.asarray(pose["imputed"], bool)
        movers[1].move_3d(view, imputed)
        movers[2].move_3d(view, imputed)
        title.set_text(f"RepNet lift, model {model_id}: {caption}")
        if progress is not None:
            progress(i, len(frames))

    if writer is None:  # GIF
        moving = [title, axes[0].title, *(a for m in movers for a in (*m.lines, *m.collections))]
        _write_gif(output, fig, moving, move, len(frames), fps)
    else:
        with writer.saving(fig, str(output), dpi=ANIMATION_DPI):
            for i in range(len(frames)):
                move(i)
                writer.grab_frame()
    plt.close(fig)


def _write_gif(
    output: Path, fig: Any, moving: list[Any], move: Callable[[int], None], count: int, fps: int
) -> None:
    """Blit `count` frames (move(i) sets frame i's data on the `moving` artists) into a GIF."""
    from PIL import Image

    for artist in moving:
        artist.set_animated(True)  # left out of full draws: the background is what stays still
    canvas = fig.canvas
    canvas.draw()
    background = canvas.copy_from_bbox(fig.bbox)
    images: list[Any] = []
    palette = None
    for i in range(count):
        move(i)
        canvas.restore_region(background)
        for artist in moving:
            fig.draw_artist(artist)
        frame = Image.fromarray(np.asarray(canvas.buffer_rgba())[..., :3])
        # one palette for every frame, from the first (the figure's few colours and their blends):
        # mapping onto it costs 1 ms a frame, a palette of each frame's own 35 ms
        palette = palette or frame.quantize(method=Image.Quantize.FASTOCTREE)
        images.append(frame.quantize(palette=palette, dither=Image.Dither.NONE))
    images[0].save(output, save_all=True, append_images=images[1:], duration=round(1000 / fps), loop=0)


ANIMATION_DPI = 60


class _Movers:
    """The artists _draw made on one panel, in the order it made them, and how to move them to
    another pose: 2D (detector points, input bones, reprojection bones, imputed marks) or 3D (bones,
    joints, imputed rings)."""

    def __init__(self, ax: Any) -> None:
        self.ax = ax
        self.lines = list(ax.lines)
        self.collections = list(ax.collections)

    def move_2d(
        self, detector: np.ndarray, points: np.ndarray, visible: np.ndarray, pose: dict[str, Any]
    ) -> None:
        """Move the 2D panel to a frame: (D, 2) detector points, (17, 2) model points and visibility."""
        reprojection = np.asarray(pose["reprojection"], dtype=np.float64)
        imputed = np.asarray(pose["imputed"], dtype=bool)
        bones = _bones(MODEL_PARENTS)
        everywhere = np.ones(len(MODEL_JOINTS), bool)
        for k, (p, c) in enumerate(bones):  # _draw_2d's lines: the input's bones, then the reprojection's
            self.lines[k].set_data(*_bone_2d(points, visible, p, c))
            self.lines[len(bones) + k].set_data(*_bone_2d(reprojection, everywhere, p, c))
        self.collections[0].set_offsets(detector)
        self.collections[1].set_offsets(reprojection[imputed])
        self.ax.set_title(
            self.ax.get_title().split("\n")[0] + f"\nerror {pose['reprojection_error_px']:.1f} px"
        )

    def move_3d(self, view: np.ndarray, imputed: np.ndarray) -> None:
        """Move a 3D panel to a frame: (17, 3) plotted x, depth, up."""
        for line, (p, c) in zip(self.lines, _bones(MODEL_PARENTS), strict=True):
            line.set_data_3d(view[[p, c], 0], view[[p, c], 1], view[[p, c], 2])
        joints, rings = self.collections
        joints._offsets3d = (view[:, 0], view[:, 1], view[:, 2])
        rings._offsets3d = (view[imputed, 0], view[imputed, 1], view[imputed, 2])
        for markers in (joints, rings):  # a blitted frame draws them without the axes' projection pass
            markers.do_3d_projection()


ANIMATIONS = (".gif", ".mp4")


def plot_lift_file(
    path: Path,
    output: Path,
    index: int = 0,
    person: int = 0,
    fps: int = 10,
    progress: Callable[[int, int], None] | None = None,
    track: str | None = None,
) -> int:
    """Plot pose `index` of a `repnet lift` output file, or, when `output` is a .gif or .mp4, animate
    the poses of `person` (or, given, of `track`: one tracked person) frame by frame. Returns the
    number of poses drawn. Raises ValueError on a malformed file."""
    data = json.loads(path.read_text())
    poses = data.get("poses") if isinstance(data, dict) else None
    if not isinstance(poses, list) or data.get("format") not in FORMATS:
        raise ValueError(f"{path}: not a `repnet lift` output (needs 'format' and 'poses')")
    model_id = str(data.get("model_id", ""))

    def keypoints(pose: dict[str, Any]) -> np.ndarray:
        rows = pose["input"]["keypoints"]
        return np.array([[np.nan, np.nan] if p is None else p for p in rows], dtype=float)

    if output.suffix in ANIMATIONS:
        if track is None:
            chosen = [(i, p) for i, p in enumerate(poses) if p.get("person", 0) == person]
            who = f"person {person}"
        else:
            chosen = [(i, p) for i, p in enumerate(poses) if p.get("track_id") == track]
            who = f"track {track}"
        if not chosen:
            raise ValueError(f"{path}: no pose of {who}")
        frames = [(keypoints(p), p, f"frame {p.get('frame', i)}, {who}") for i, p in chosen]
        animate_poses(output, data["format"], frames, model_id, fps, progress)
        return len(frames)
    if not -len(poses) <= index < len(poses):
        raise ValueError(f"{path}: pose index {index} out of range, the file has {len(poses)} poses")
    plot_pose(output, data["format"], keypoints(poses[index]), poses[index], model_id)
    return 1
