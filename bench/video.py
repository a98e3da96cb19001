"""How fast `repnet video` runs on this CPU: decode, the 2D detector and the lifter timed apart, and
the whole command end to end, for one person at 640 x 480 and several people at 1280 x 720.

    python -m bench.video --clip CLIP [--frames 200] [--threads 2] [--out runs/bench/video.json]

CLIP is a video of several people at 1280 x 720 (OpenPose's examples/media/video.avi: 205 frames at
50 fps, github.com/CMU-Perceptual-Computing-Lab/openpose; not in this repository: fetch it). The
one-person case is the same clip cut to its left 960 x 720 (4:3), scaled to 640 x 480 and followed
with --max-people 1; both are encoded once into a temporary folder (H.264) before anything is timed.
Every stage runs in this process, one after the other, as the command runs them (the detector's
onnxruntime threads: --threads); the lift is `--local` with the offline temporal model.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

if __package__ in (None, ""):  # `python bench/video.py`
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench.stats import fmt, machine, report
from repnet.cli.lift import lift_poses
from repnet.cli.main import build_parser
from repnet.cli.main import main as repnet
from repnet.cli.video import DEFAULT_THRESHOLD, FORMAT, detect_poses
from repnet.io.overlay import write_overlay
from repnet.io.video import open_clip
from repnet.runtime.detector import PoseDetector


@dataclass(frozen=True)
class Case:
    """One measured setting: the clip and how many people are followed."""

    name: str
    width: int
    height: int
    max_people: int


CASES = (Case("one person", 640, 480, 1), Case("several people", 1280, 720, 4))


def make_clip(source: Path, case: Case, frames: int, folder: Path) -> Path:
    """The first `frames` frames of `source` as `case` wants them (4:3 cut on the left for a 4:3 size),
    encoded as H.264 in `folder`."""
    import av

    out = folder / f"{case.width}x{case.height}.mp4"
    with av.open(str(source)) as inp, av.open(str(out), "w") as container:
        rate = inp.streams.video[0].average_rate
        stream = container.add_stream("libx264", rate=rate)
        stream.width, stream.height, stream.pix_fmt = case.width, case.height, "yuv420p"
        for i, frame in enumerate(inp.decode(video=0)):
            if i >= frames:
                break
            image = frame.to_ndarray(format="rgb24")
            aspect = case.width / case.height
            image = image[:, : int(round(image.shape[0] * aspect))]
            picture = av.VideoFrame.from_ndarray(np.ascontiguousarray(image), format="rgb24")
            container.mux(
                stream.encode(picture.reformat(width=case.width, height=case.height, format="yuv420p"))
            )
        container.mux(stream.encode(None))
    return out


def measure(clip: Path, case: Case, threads: int) -> dict[str, Any]:
    """Each stage's seconds over the clip, and the command's wall time."""
    started = time.perf_counter()
    video = open_clip(str(clip))
    images = list(video.frames())
    video.close()
    decode = time.perf_counter() - started
    detector = PoseDetector(max_people=case.max_people, threads=threads)
    started = time.perf_counter()
    people = [len(detector.track(image)) for image in images]
    detect = time.perf_counter() - started
    args = build_parser().parse_args(["video", str(clip), "--local", "--max-people", str(case.max_people)])
    video = open_clip(str(clip))
    poses, _ = detect_poses(video, args, lambda total, unit: None, keep=False)
    video.close()
    started = time.perf_counter()
    lifted, _ = lift_poses(args, poses, FORMAT, None, lambda total, unit: None)
    lift = time.perf_counter() - started
    with tempfile.TemporaryDirectory() as folder:
        started = time.perf_counter()
        write_overlay(Path(folder) / "out.mp4", iter(images), lifted, video.fps, DEFAULT_THRESHOLD)
        overlay = time.perf_counter() - started
        out = Path(folder) / "out.json"
        command = [
            "video",
            str(clip),
            "--local",
            "--max-people",
            str(case.max_people),
            "--threads",
            str(threads),
        ]
        started = time.perf_counter()
        if repnet([*command, "-o", str(out)]) != 0:
            raise RuntimeError(f"repnet {' '.join(command)} failed")
        end_to_end = time.perf_counter() - started
    n = len(images)
    return {
        "case": case.name,
        "size": f"{case.width} x {case.height}",
        "frames": n,
        "people_per_frame": float(np.mean(people)),
        "poses_lifted": len(lifted.results),
        "decode_ms_per_frame": 1000 * decode / n,
        "detector_ms_per_frame": 1000 * detect / n,
        "lifter_ms_per_frame": 1000 * lift / n,
        "overlay_mp4_ms_per_frame": 1000 * overlay / n,
        "end_to_end_s": end_to_end,
        "end_to_end_frames_per_s": n / end_to_end,
        "stages_frames_per_s": n / (decode + detect + lift),
    }


def render(result: dict[str, Any]) -> str:
    """The markdown table of the cases."""
    lines = [
        f"`repnet video` on {result['machine']['cpus']} CPUs ({result['machine']['cpu']}), detector threads "
        f"{result['threads']}",
        "",
        "| case | size | frames | people/frame | decode ms/frame | detector ms/frame | lifter ms/frame "
        "| stages frames/s | end to end frames/s | -o .mp4 drawing ms/frame |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in result["cases"]:
        lines.append(
            f"| {r['case']} | {r['size']} | {r['frames']} | {fmt(r['people_per_frame'], 1)} "
            f"| {fmt(r['decode_ms_per_frame'], 1)} | {fmt(r['detector_ms_per_frame'], 1)} "
            f"| {fmt(r['lifter_ms_per_frame'], 2)} | {fmt(r['stages_frames_per_s'], 1)} "
            f"| {fmt(r['end_to_end_frames_per_s'], 1)} | {fmt(r['overlay_mp4_ms_per_frame'], 1)} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Measure both cases on the clip; print the table, write the JSON."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--clip", type=Path, required=True, help="a 1280 x 720 video of several people")
    parser.add_argument("--frames", type=int, default=200, help="frames of it to use (default 200)")
    parser.add_argument(
        "--threads", type=int, default=2, help="the detector's onnxruntime threads (default 2)"
    )
    parser.add_argument("--out", type=Path, default=Path("runs/bench/video.json"))
    args = parser.parse_args(argv)
    cases = []
    with tempfile.TemporaryDirectory() as folder:
        for case in CASES:
            clip = make_clip(args.clip, case, args.frames, Path(folder))
            cases.append(measure(clip, case, args.threads))
    result = {"machine": machine(), "threads": args.threads, "clip": str(args.clip), "cases": cases}
    return report(result, args.out, render)


if __name__ == "__main__":
    sys.exit(main())
