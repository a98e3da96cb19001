"""`repnet video -o out.mp4|.gif`: the clip with each person's 2D skeleton drawn on it, beside a panel
where their 3D poses turn slowly about the vertical axis. Drawn with Pillow (lines on the frame, no
figure per frame: matplotlib's 3D axes cost about 30 ms a frame, bench/plot_speed.py) and encoded with
PyAV (H.264) or Pillow (GIF)."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from repnet.core.formats import FORMATS, MODEL_JOINTS, MODEL_PARENTS, to_model_joints
from repnet.io.output import Lifted
from repnet.io.plot import CENTRE, LEFT, RIGHT

VIDEO_SUFFIXES = (".mp4", ".gif")
TURN_SECONDS = 8.0  # one turn of the 3D panel
PANEL_MM = 2400.0  # the 3D panel's height in mm of pose
MAX_GIF_WIDTH = 640  # a GIF is scaled down to this width: it stores every pixel of every frame
_RGB = {LEFT: (31, 119, 180), RIGHT: (214, 39, 40), CENTRE: (235, 235, 235)}


def _colour(joint: str) -> tuple[int, int, int]:
    """A bone's colour by its child joint's side (the subject's left blue, right red), as plot.py."""
    side = LEFT if joint.startswith("left_") else RIGHT if joint.startswith("right_") else CENTRE
    return _RGB[side]


BONES = [(p, c, _colour(MODEL_JOINTS[c])) for c, p in enumerate(MODEL_PARENTS) if p >= 0]


def people_by_frame(lifted: Lifted, threshold: float) -> dict[int, list[tuple[np.ndarray, np.ndarray, Any]]]:
    """Each frame's people: their 2D input on the model's joints (17, 2) px, which of them are
    visible (17,), and their result."""
    poses = lifted.poses
    fmt = FORMATS[str(lifted.document["format"])]
    conf = np.ones(poses.points.shape[:2]) if poses.confidence is None else poses.confidence
    seen = np.isfinite(poses.points).all(axis=2) & (conf >= threshold)
    points, visible, _, _ = to_model_joints(fmt, np.nan_to_num(poses.points), seen)
    out: dict[int, list[tuple[np.ndarray, np.ndarray, Any]]] = {}
    for i, result in enumerate(lifted.results):
        out.setdefault(int(poses.frame[i]), []).append((points[i], visible[i], result))
    return out


def draw_frame(
    image: np.ndarray, people: Sequence[tuple[np.ndarray, np.ndarray, Any]], turn: float
) -> np.ndarray:
    """(H, W + H, 3) uint8: the RGB frame (H, W, 3) with the people's 2D skeletons, and beside it a
    square panel of their 3D poses (pose_3d_camera) seen from `turn` radians about the vertical,
    placed left to right as they stand in the frame."""
    from PIL import Image, ImageDraw

    height, width = image.shape[:2]
    canvas = Image.new("RGB", (width + height, height), (24, 24, 28))
    canvas.paste(Image.fromarray(image), (0, 0))
    draw = ImageDraw.Draw(canvas)
    line = max(2, height // 180)
    for points, visible, _ in people:
        for p, c, colour in BONES:
            if visible[p] and visible[c]:
                draw.line([tuple(points[p]), tuple(points[c])], fill=colour, width=line)
    scale = height / PANEL_MM
    cos, sin = np.cos(turn), np.sin(turn)
    for points, visible, result in people:
        pose = np.asarray(result.pose_3d_camera, dtype=np.float64)  # (17, 3) mm: x right, y down, z depth
        pose = pose - pose[0]
        x = cos * pose[:, 0] + sin * pose[:, 2]
        spot = points[visible].mean(axis=0)[0] / width if visible.any() else 0.5
        u = width + height * (0.15 + 0.7 * spot) + scale * x
        v = height * 0.5 + scale * pose[:, 1]
        for p, c, colour in BONES:
            draw.line([(u[p], v[p]), (u[c], v[c])], fill=colour, width=line)
    return np.asarray(canvas)


def write_overlay(
    path: Path,
    frames: Iterable[np.ndarray],
    lifted: Lifted,
    fps: float,
    threshold: float,
    advance: Callable[[], None] | None = None,
) -> list[Path]:
    """Write the drawn clip (draw_frame) to `path` (.mp4: H.264 with PyAV, .gif with Pillow) at `fps`;
    `advance` is called after each frame. The files written."""
    people = people_by_frame(lifted, threshold)
    drawn = (
        draw_frame(image, people.get(i, []), 2 * np.pi * i / (fps * TURN_SECONDS))
        for i, image in enumerate(frames)
    )
    if path.suffix.lower() == ".gif":
        _write_gif(path, drawn, fps, advance)
    else:
        _write_mp4(path, drawn, fps, advance)
    return [path]


def _write_mp4(
    path: Path, drawn: Iterable[np.ndarray], fps: float, advance: Callable[[], None] | None
) -> None:
    """H.264 in an MP4, yuv420p (what players take): the frame cut to even sides."""
    from fractions import Fraction

    import av

    with av.open(str(path), "w") as container:
        stream = None
        for image in drawn:
            image = image[: image.shape[0] // 2 * 2, : image.shape[1] // 2 * 2]
            if stream is None:
                stream = container.add_stream("libx264", rate=Fraction(fps).limit_denominator(1001))
                stream.width, stream.height = image.shape[1], image.shape[0]
                stream.pix_fmt = "yuv420p"
                # superfast: 24 ms a 2000 x 720 frame where veryfast took 42 (1.5 x the bytes)
                stream.options = {"crf": "23", "preset": "superfast"}
            frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(image), format="rgb24")
            container.mux(stream.encode(frame))
            if advance is not None:
                advance()
        if stream is not None:
            container.mux(stream.encode(None))


def _write_gif(
    path: Path, drawn: Iterable[np.ndarray], fps: float, advance: Callable[[], None] | None
) -> None:
    """An animated GIF, scaled down to MAX_GIF_WIDTH."""
    from PIL import Image

    images = []
    for image in drawn:
        picture = Image.fromarray(image)
        if picture.width > MAX_GIF_WIDTH:
            picture = picture.resize((MAX_GIF_WIDTH, round(picture.height * MAX_GIF_WIDTH / picture.width)))
        images.append(picture)
        if advance is not None:
            advance()
    if images:
        duration = max(20, round(1000 / fps))
        images[0].save(path, save_all=True, append_images=images[1:], duration=duration, loop=0)
