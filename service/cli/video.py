"""`repnet video CLIP|DEVICE -o OUT`: the people of a video found in 2D (BlazePose in this process,
repnet.runtime.detector), tracked and lifted as `repnet lift` lifts a file (through the service or
--local), and written as `repnet lift` writes, or drawn over the clip (.mp4, .gif)."""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from repnet.cli.lift import lift_poses, say, tell_written
from repnet.cli.options import add_lift_options
from repnet.io.output import WRITERS, check_output, write_output
from repnet.io.overlay import VIDEO_SUFFIXES, write_overlay
from repnet.io.poses import InputFileError, Poses
from repnet.io.video import Clip, open_clip

FORMAT = "mediapipe33"  # repnet.core.formats: BlazePose's 33 landmarks in px
DEFAULT_THRESHOLD = 0.5  # a landmark's visibility below it counts as missing (the overlay's too)
Bar = Callable[[int, str], Any]


def add_parser(sub: Any) -> None:
    """The `video` subcommand on the `repnet` parser's subparsers."""
    video = sub.add_parser("video", help="find people in a video or camera, lift them to 3D")
    video.add_argument(
        "input",
        help="a video file (anything FFmpeg reads: .mp4, .mov, .avi...) or a camera: /dev/video0 or 0",
    )
    video.add_argument(
        "-o",
        "--output",
        type=Path,
        help=f"output file by its suffix ({', '.join([*WRITERS, *VIDEO_SUFFIXES])}; default: JSON on "
        "stdout): what `repnet lift -o` writes, or the clip with the 2D skeletons beside the turning "
        "3D poses (.mp4 H.264, .gif)",
    )
    video.add_argument("--max-people", type=int, default=4, help="people followed at once (default 4)")
    video.add_argument(
        "--redetect-every",
        type=int,
        default=10,
        help="run the person detector every N frames to find people who came in (default 10; 0: only "
        "when someone is lost); between, each person is followed from the previous frame",
    )
    video.add_argument(
        "--zoom",
        type=int,
        choices=(0, 1, 2),
        default=1,
        help="the person detector's closer views of a frame: 0 the whole frame (MediaPipe's), 1 also "
        "squares of its height (default; a wide frame's people), 2 also of half its height (smaller "
        "people, slower detection)",
    )
    video.add_argument("--max-frames", type=int, help="stop after this many frames (a camera: else Ctrl-C)")
    video.add_argument("--threads", type=int, default=2, help="threads of the detector's models (default 2)")
    add_lift_options(
        video,
        "offline for a file, causal for a camera",
        "the video's, said in the output",
    )
    video.set_defaults(confidence_threshold=DEFAULT_THRESHOLD)


def check_args(args: argparse.Namespace) -> str | None:
    """What is wrong with the flags, if anything."""
    if args.batch_size < 1:
        return "--batch-size must be at least 1"
    if args.max_people < 1:
        return "--max-people must be at least 1"
    if args.redetect_every < 0:
        return "--redetect-every must be 0 or more"
    if args.max_frames is not None and args.max_frames < 1:
        return "--max-frames must be at least 1"
    if args.threads < 1:
        return "--threads must be at least 1"
    return None


def _frames(clip: Clip, limit: int | None, bar: Any) -> Iterator[np.ndarray]:
    """The clip's frames, the bar advanced with frames/s."""
    start = time.perf_counter()
    for i, image in enumerate(clip.frames(limit)):
        yield image
        if bar is not None:
            bar.update(1)
            bar.set_postfix_str(f"{(i + 1) / (time.perf_counter() - start):.1f} frames/s", refresh=False)


def detect_poses(
    clip: Clip, args: argparse.Namespace, progress_bar: Bar, keep: bool
) -> tuple[Poses, list[np.ndarray]]:
    """Every frame's people (BlazePose, followed from frame to frame) as poses of `FORMAT`, x, y in
    px and each landmark's visibility as its confidence; the frames themselves when `keep`. A camera
    is read until Ctrl-C (or --max-frames): the frames done by then are kept. InputFileError when no
    frame has a person."""
    from repnet.runtime.detector import PoseDetector

    detector = PoseDetector(
        max_people=args.max_people, redetect_every=args.redetect_every, zoom=args.zoom, threads=args.threads
    )
    found: list[tuple[np.ndarray, list[Any]]] = []  # each frame, as one append: Ctrl-C leaves it whole
    total = (
        args.max_frames
        if clip.frame_count is None
        else min(clip.frame_count, args.max_frames or clip.frame_count)
    )
    bar = progress_bar(total or 0, "frame")
    try:
        for image in _frames(clip, args.max_frames, bar):
            people = detector.track(image)
            found.append((image if keep else np.empty(0), people))
    except KeyboardInterrupt:
        if not clip.live:
            raise
        say(f"camera stopped (Ctrl-C) after {len(found)} frames: lifting them")
    finally:
        if bar is not None:
            bar.close()
    if clip.broken is not None:
        say(f"warning: {clip.broken}; the frames before it are used")
    count = len(found)
    if count == 0:
        raise InputFileError(f"{clip.source}: the video has no frames")
    rows = [(i, k, person) for i, (_, people) in enumerate(found) for k, person in enumerate(people)]
    if not rows:
        raise InputFileError(f"{clip.source}: no person found in its {count} frame{'s' * (count != 1)}")
    poses = Poses(
        np.stack([p.points for _, _, p in rows]),
        np.stack([p.visibility for _, _, p in rows]),
        FORMAT,
        np.array([i for i, _, _ in rows]),
        np.array([k for _, k, _ in rows]),
        fps=clip.fps,
    )
    say(f"found {len(rows)} poses in {count} frames ({clip.width} x {clip.height}, {clip.fps:g} fps)")
    return poses, [image for image, _ in found] if keep else []


def run(args: argparse.Namespace, progress_bar: Bar) -> int:
    """`repnet video`; the exit status (0), or an error the command's main reports."""
    out = args.output
    video_out = out is not None and out.suffix.lower() in VIDEO_SUFFIXES
    if out is not None and not video_out:
        check_output(out, args.overwrite)
    if video_out and out.exists() and not args.overwrite:
        raise InputFileError(f"-o {out}: it exists; --overwrite replaces it")
    if video_out and not out.parent.is_dir():
        raise InputFileError(f"-o {out}: the folder {out.parent} does not exist")
    clip = open_clip(args.input)
    try:
        poses, kept = detect_poses(clip, args, progress_bar, keep=video_out and clip.live)
    finally:
        clip.close()
    temporal = args.temporal or ("causal" if clip.live else None)
    lifted, choice = lift_poses(args, poses, FORMAT, temporal, progress_bar)
    lifted.document["video"] = {
        "source": args.input, "width": clip.width, "height": clip.height, "fps": clip.fps,
        "frames": int(poses.frame.max()) + 1,
    }  # fmt: skip
    if out is None:
        print(json.dumps(lifted.document, allow_nan=False))
        return 0
    if not video_out:
        tell_written(write_output(out, lifted), lifted, choice)
        return 0
    frames_written = lifted.document["video"]["frames"]
    bar = progress_bar(frames_written, "frame")
    source = iter(kept) if clip.live else _reread(args.input, frames_written)
    try:
        files = write_overlay(
            out,
            source,
            lifted,
            clip.fps,
            args.confidence_threshold,
            None if bar is None else lambda: bar.update(1),
        )
    finally:
        if bar is not None:
            bar.close()
    tell_written(files, lifted, choice)
    return 0


def _reread(source: str, frames: int) -> Iterator[np.ndarray]:
    """The clip's first `frames` frames again (a file: not held in memory between the passes)."""
    clip = open_clip(source)
    try:
        yield from clip.frames(frames)
    finally:
        clip.close()
