"""The 2D poses `repnet adapt` learns from: every file `repnet lift` reads, through the service's own
input rules, as the model's 17 joints (the poses a request would reject are skipped, and counted)."""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from repnet.core.errors import echo
from repnet.core.format_hints import alias_of, alternatives_note, hint_for
from repnet.core.formats import DEFAULT_FORMAT, FORMATS
from repnet.core.inputs import MODEL_ID, MODEL_ID_RULE, Limits, PoseInput
from repnet.core.keypoints import prepare_poses
from repnet.core.links import kept_links, shifted
from repnet.io.pose_file import Progress, read_input
from repnet.io.poses import InputFileError, Poses


def format_error(name: str) -> str:
    """Why `name` is no format, with the one it may mean."""
    alias = alias_of(name)
    means = f"; for {FORMATS[alias].description} use --format {alias}" if alias else ""
    return f"unknown format {echo(name)}; expected one of {', '.join(FORMATS)}{means}"


def resolve_format(
    poses: Poses, given: str | None, source: str, say: Callable[[str], None] | None = None
) -> str:
    """The keypoint format of a file's poses: `given` (--format), else the file's, else h36m17;
    InputFileError when the poses' joint count is not that format's, with a hint at the right one.
    Without --format, `say` is told of the other formats with as many joints, which the file cannot
    tell from its own (body25: body25b; format_hints.alternatives_note)."""
    fmt = given or poses.format or DEFAULT_FORMAT
    if given is None and fmt in FORMATS and say is not None and (note := alternatives_note(fmt)):
        say(note)
    if fmt not in FORMATS:
        raise InputFileError(format_error(fmt))
    if poses.points.shape[1] != len(FORMATS[fmt].joint_names):
        first = poses.points[0]
        present = ~np.isnan(first).any(axis=1)
        hint = hint_for(first, present, fmt, flag=True) or "; pick the format with --format"
        raise InputFileError(
            f"{source}: poses have {poses.points.shape[1]} joints, format {fmt} has "
            f"{len(FORMATS[fmt].joint_names)}{hint}"
        )
    return fmt


@dataclass(frozen=True)
class AdaptInput:
    """The usable poses of every input, in input order, in the model's joints."""

    points: np.ndarray  # (N, 17, 2) float32 px, 0 where not visible
    visible: np.ndarray  # (N, 17) float32 in {0, 1}
    counts: tuple[int, ...]  # usable poses per input
    skipped: int  # poses the service's input rules reject (too few joints, out of range, ...)
    # (N,) per pose the row of the same person's pose in the frame before it, -1 where none
    # (Poses.previous_frames, among the usable poses of all inputs)
    previous: np.ndarray


def read_adapt_input(
    specs: Sequence[str],
    fmt: str | None,
    threshold: float | None,
    image_size: tuple[float, float] | None,
    progress: Progress,
) -> AdaptInput:
    """Read each input (a file, a folder or a glob of frame files) and keep the poses the service
    would lift, converted to the model's joints as a request converts them."""
    limits = Limits()  # the service's own rules; prepare_poses does not cap the count (check_request would)
    points: list[np.ndarray] = []
    visible: list[np.ndarray] = []
    previous: list[np.ndarray] = []
    counts: list[int] = []
    skipped = 0
    for spec in specs:
        poses = read_input(spec, progress, image_size)
        if not len(poses.points):
            raise InputFileError(f"{spec}: no poses")
        name = resolve_format(poses, fmt, spec)
        conf = poses.confidence
        inputs = [
            PoseInput(p, ~np.isnan(p).any(axis=1), None if conf is None else conf[i], name)
            for i, p in enumerate(poses.points)
        ]
        prepared = prepare_poses(inputs, limits, threshold)
        kept = prepared.inputs
        skipped += sum(1 for found in prepared.violations if found)
        usable = np.array([not found for found in prepared.violations], dtype=bool)
        previous.append(shifted(kept_links(poses.previous_frames(), usable), sum(counts)))
        points.append(kept.keypoints_2d.astype(np.float32))
        visible.append(kept.visible.astype(np.float32))
        counts.append(len(kept))
    total = sum(counts)
    if total == 0:
        raise InputFileError("no usable poses in the inputs (each needs enough visible joints)")
    return AdaptInput(
        np.concatenate(points), np.concatenate(visible), tuple(counts), skipped, np.concatenate(previous)
    )


def run(args: argparse.Namespace) -> int:
    """`repnet adapt`: read the inputs here, adapt in repnet.train.adapt_cli (the `train` extra)."""
    try:
        from repnet.train import adapt_cli
    except ImportError as err:
        hint = "pip install 'repnet[train]', or pip install -e '.[train]' in a checkout"
        print(f"repnet: error: adapt needs the train extra ({err.name} is missing): {hint}", file=sys.stderr)
        return 2
    size = None if args.image_size is None else (args.image_size[0], args.image_size[1])
    data = read_adapt_input(args.input, args.format, args.confidence_threshold, size, lambda files: files)
    return adapt_cli.run(args, data.points, data.visible, data.counts, data.skipped, data.previous)


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser], size: Any, fmt: Any) -> None:
    """`repnet adapt`'s flags (its work is repnet.train.adapt_cli's, with the `train` extra). size and
    fmt: the --image-size and --format value parsers `repnet lift` uses."""
    adapt = sub.add_parser(
        "adapt",
        help="adapt a model to your own unlabeled 2D detections (needs the train extra)",
        description="Fine-tune a model on 2D poses alone, the paper's weak supervision: no 3D is needed. "
        "Writes an ONNX model the service serves (--model-path, REPNET_MODEL_DIR) and prints a report "
        "on a held-out part of the inputs; a model that got worse there is not written (--force).",
    )
    adapt.add_argument("input", nargs="+", help="files, folders or globs `repnet lift` reads")
    adapt.add_argument("-o", "--output", type=Path, required=True, help="the adapted model (.onnx)")
    adapt.add_argument("--model", help="the model to adapt (an .onnx file; default: the bundled one)")
    adapt.add_argument(
        "--model-id",
        type=model_id_flag,
        help=f"the adapted model's id (default: the output's name): {MODEL_ID_RULE}",
    )
    adapt.add_argument(
        "--format", type=fmt, metavar="FORMAT", help="keypoint format (default: file's, h36m17)"
    )
    adapt.add_argument(
        "--image-size",
        type=size,
        nargs=2,
        metavar=("W", "H"),
        help="width and height in px of normalised [0, 1] inputs (MediaPipe rows)",
    )
    adapt.add_argument(
        "--confidence-threshold", type=threshold_flag, help="joints below it count as missing, in [0, 1]"
    )
    adapt.add_argument(
        "--minutes",
        type=_positive(float),
        help="wall-time limit (default 25); the run checkpoints, --resume goes on",
    )
    adapt.add_argument(
        "--steps",
        type=_positive(int),
        help="training steps in all (default: chosen from the held-out 2D and said: 500 on clips of "
        "consecutive frames, 2000 on spread poses)",
    )
    adapt.add_argument("--threads", type=_positive(int), default=0, help="torch threads (default: all cores)")
    adapt.add_argument("--resume", action="store_true", help="go on from the last checkpoint of this run")
    adapt.add_argument(
        "--holdout-fraction",
        type=_fraction,
        default=0.1,
        help="the last fraction of each input held out for the report (default 0.1)",
    )
    adapt.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    adapt.add_argument("--force", action="store_true", help="write the model even when it got worse")
    adapt.add_argument(
        "--run-dir", type=Path, help="checkpoint folder (default: one in ~/.cache/repnet/adapt)"
    )
    adapt.add_argument(
        "--prior-poses",
        type=_positive(int),
        default=100_000,
        help="3D poses drawn from the shipped pose prior for the run (default 100000)",
    )
    adapt.add_argument(
        "--prior",
        type=Path,
        help="the pose prior the 3D poses are drawn from (an .npz that python -m repnet.train.prior "
        "writes; default: the shipped one, fitted to Human3.6M)",
    )
    adapt.add_argument(
        "--reprojection-weight",
        type=_non_negative,
        help="weight of the paper's reprojection term on your 2D (default 0.1)",
    )
    adapt.add_argument(
        "--adversarial-weight",
        type=_non_negative,
        help="weight of the critic's Wasserstein term on the answers to your 2D (default 0.1)",
    )
    adapt.add_argument(
        "--smoothness-weight",
        type=_non_negative,
        help="weight of the smoothness of the answers to consecutive frames of one person (default 0)",
    )
    adapt.add_argument(
        "--residuals",
        choices=["mean", "pose", "off"],
        help="your detector's errors in the synthetic 2D: their mean per joint (default), each pose's, none",
    )


def _positive(kind: type) -> Any:
    def parse(text: str) -> Any:
        try:
            value = kind(text)
        except ValueError:
            value = None
        if value is None or not math.isfinite(value) or value <= 0:  # nan and inf are no limit
            raise argparse.ArgumentTypeError(f"expected a finite number above 0, got {text!r}")
        return value

    return parse


def _between(low: float, high: float, what: str) -> Any:
    """A flag's float in [low, high); the error names the range as `what`."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if not low <= value < high:
            raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}")
        return value

    return parse


def model_id_flag(text: str) -> str:
    """--model-id: an id the service serves (core.inputs.MODEL_ID)."""
    if MODEL_ID.fullmatch(text) is None:
        raise argparse.ArgumentTypeError(f"expected {MODEL_ID_RULE}, got {text!r}")
    return text


def threshold_flag(text: str) -> float:
    """--confidence-threshold: a number in [0, 1], as the service's rule (core.keypoints.check_threshold)."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not 0.0 <= value <= 1.0:  # nan fails both
        raise argparse.ArgumentTypeError(f"expected a number in [0, 1], got {text!r}")
    return value


_non_negative = _between(0.0, math.inf, "a number >= 0")
_fraction = _between(0.0, 1.0, "a fraction in [0, 1)")
