"""Figures of lifted poses: the 2D input with its reprojection, and the 3D pose from two viewpoints."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from service.formats import FORMATS, MODEL_JOINTS, MODEL_PARENTS, to_model_joints

LEFT, RIGHT, CENTRE = "#1f77b4", "#d62728", "#444444"  # the subject's left blue, right red


def side_colour(joint: str) -> str:
    return LEFT if joint.startswith("left_") else RIGHT if joint.startswith("right_") else CENTRE


def _bones(parents: tuple[int, ...]) -> list[tuple[int, int]]:
    """(parent, child) pairs; a bone takes the colour of its child's side."""
    return [(p, c) for c, p in enumerate(parents) if p >= 0]


def _draw_2d(ax: Any, points: np.ndarray, visible: np.ndarray, **style: Any) -> None:
    """Bones of the (17, 2) skeleton between visible joints, coloured by side."""
    for p, c in _bones(MODEL_PARENTS):
        if visible[p] and visible[c]:
            ax.plot(points[[p, c], 0], points[[p, c], 1], color=side_colour(MODEL_JOINTS[c]), **style)


def _draw_3d(ax: Any, pose: np.ndarray, imputed: np.ndarray, title: str, elev: float, azim: float) -> None:
    """(17, 3) pose in a camera-like frame (x right, y down, z depth) shown with up pointing up."""
    x, depth, up = pose[:, 0], pose[:, 2], -pose[:, 1]
    for p, c in _bones(MODEL_PARENTS):
        ax.plot(x[[p, c]], depth[[p, c]], up[[p, c]], color=side_colour(MODEL_JOINTS[c]), linewidth=2.5)
    colours = [side_colour(j) for j in MODEL_JOINTS]
    ax.scatter(x, depth, up, c=colours, s=14, depthshade=False)
    ax.scatter(x[imputed], depth[imputed], up[imputed], facecolors="none", edgecolors="k", s=60)
    centre = np.array([x.mean(), depth.mean(), up.mean()])
    half = max(np.ptp(x), np.ptp(depth), np.ptp(up)) / 2 + 50
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


def plot_pose(
    output: Path, fmt_name: str, keypoints: np.ndarray, pose: dict[str, Any], model_id: str
) -> None:
    """Write a figure of one lifted pose: `keypoints` (K, 2) in `fmt_name`, NaN where missing;
    `pose` the reply's fields (pose_3d_camera, reprojection, imputed, reprojection_error_px)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    fmt = FORMATS[fmt_name]
    present = ~np.isnan(keypoints).any(axis=1)
    model_points, model_visible, _, _ = to_model_joints(fmt, keypoints[None], present[None])
    reprojection = np.asarray(pose["reprojection"], dtype=np.float64)  # (17, 2)
    imputed = np.asarray(pose["imputed"], dtype=bool)
    fig = plt.figure(figsize=(16, 5.5), layout="constrained")
    ax = fig.add_subplot(1, 3, 1)
    ax.scatter(keypoints[present, 0], keypoints[present, 1], s=10, color="0.6", label="detector joints")
    _draw_2d(ax, model_points[0], model_visible[0], linewidth=2.5)
    _draw_2d(ax, reprojection, np.ones(17, bool), linewidth=1.2, linestyle="--")
    ax.scatter(reprojection[imputed, 0], reprojection[imputed, 1], marker="x", color="k", s=40)
    shown = np.concatenate([keypoints[present], reprojection])  # a square window around both
    centre, half = (shown.max(axis=0) + shown.min(axis=0)) / 2, np.ptp(shown, axis=0).max() * 0.6 + 1
    ax.set_xlim(centre[0] - half, centre[0] + half)
    ax.set_ylim(centre[1] + half, centre[1] - half)  # image y points down
    ax.set_aspect("equal")
    ax.set_xlabel("x (px)")
    ax.set_ylabel("y (px)")
    ax.set_title(f"2D input ({fmt_name}) and reprojection\nerror {pose['reprojection_error_px']:.1f} px")
    ax.legend(handles=[
        Line2D([], [], color=CENTRE, linewidth=2.5, label="input"),
        Line2D([], [], color=CENTRE, linewidth=1.2, linestyle="--", label="reprojection"),
        Line2D([], [], color=LEFT, label="left"), Line2D([], [], color=RIGHT, label="right"),
        Line2D([], [], marker="x", color="k", linestyle="", label="imputed"),
    ], loc="lower left", fontsize="small", framealpha=0.6)  # fmt: skip
    pose_camera = np.asarray(pose["pose_3d_camera"], dtype=np.float64)  # (17, 3)
    _draw_3d(
        fig.add_subplot(1, 3, 2, projection="3d"), pose_camera, imputed, "3D, seen from the camera", 10, -90
    )
    _draw_3d(fig.add_subplot(1, 3, 3, projection="3d"), pose_camera, imputed, "3D, seen from the side", 10, 0)
    fig.suptitle(f"RepNet lift, model {model_id}")
    fig.savefig(output, dpi=100)
    plt.close(fig)


def plot_lift_file(path: Path, output: Path, index: int = 0) -> None:
    """Plot pose `index` of a `repnet lift` output file. Raises ValueError on a malformed file."""
    data = json.loads(path.read_text())
    poses = data.get("poses") if isinstance(data, dict) else None
    if not isinstance(poses, list) or data.get("format") not in FORMATS:
        raise ValueError(f"{path}: not a `repnet lift` output (needs 'format' and 'poses')")
    if not -len(poses) <= index < len(poses):
        raise ValueError(f"{path}: pose index {index} out of range, the file has {len(poses)} poses")
    pose = poses[index]
    keypoints = np.array(
        [[np.nan, np.nan] if p is None else p for p in pose["input"]["keypoints"]], dtype=float
    )
    plot_pose(output, data["format"], keypoints, pose, str(data.get("model_id", "")))
