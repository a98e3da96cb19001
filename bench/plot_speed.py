"""How long `repnet plot` takes to animate a clip: the wall time of a GIF (and of a PNG of one pose).

    python -m bench.plot_speed [--frames 60] [--repeat 3] [--out runs/bench/plot_speed.json]

The clip is the test pose turning and walking across the image, lifted once in this process
(`repnet lift --local` with intrinsics, so the poses carry root_camera_m); the timings are of
repnet.io.plot alone (matplotlib's import included in the first run, reported apart).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

if __package__ in (None, ""):  # `python bench/plot_speed.py`
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from repnet.cli.main import main as repnet
from repnet.core.inputs import EXAMPLE_KEYPOINTS

# A person in mid-stride seen from 4.5 m (h36m17, px): the service's example person.
EXAMPLE = np.array(EXAMPLE_KEYPOINTS)


def lifted_clip(folder: Path, frames: int) -> Path:
    """A `repnet lift` output of `frames` frames of one tracked person."""
    poses = []
    for t in range(frames):
        angle = np.deg2rad(2.0 * t)
        centre = EXAMPLE.mean(axis=0)
        squeeze = np.array([np.cos(angle), 1.0])  # turning: narrower across
        points = (EXAMPLE - centre) * squeeze + centre + [4.0 * t, 0.0]
        poses.append({"keypoints": points.tolist(), "track_id": "1", "frame": t})
    clip = folder / "clip.json"
    clip.write_text(json.dumps({"poses": poses, "fps": 30}))
    out = folder / "lifted.json"
    if repnet(["lift", str(clip), "--local", "--intrinsics", "1145,1145,512,515", "-o", str(out)]) != 0:
        raise RuntimeError("repnet lift failed")
    return out


CPU_SECONDS: list[
    float
] = []  # the process's CPU time of each timed run: what a busy machine does not inflate


def timed(argv: list[str]) -> float:
    """Wall seconds `repnet` takes for argv (its CPU seconds go to CPU_SECONDS); RuntimeError if it fails."""
    started, cpu = time.perf_counter(), time.process_time()
    if repnet(argv) != 0:
        raise RuntimeError(f"repnet {' '.join(argv)} failed")
    CPU_SECONDS.append(time.process_time() - cpu)
    return time.perf_counter() - started


def run(args: argparse.Namespace) -> dict[str, Any]:
    """Time the GIF and the PNG `args.repeat` times each."""
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        lifted = lifted_clip(folder, args.frames)
        gif, png = folder / "clip.gif", folder / "pose.png"
        first = timed(["plot", str(lifted), "-o", str(gif)])  # includes importing matplotlib
        gifs = [timed(["plot", str(lifted), "-o", str(gif)]) for _ in range(args.repeat)]
        gif_cpu = CPU_SECONDS[-args.repeat :]
        pngs = [timed(["plot", str(lifted), "-o", str(png)]) for _ in range(args.repeat)]
        size = gif.stat().st_size
    return {
        "command": " ".join(["python -m bench.plot_speed", *sys.argv[1:]]),
        "frames": args.frames,
        "gif_first_s": round(first, 2),
        "gif_s": [round(t, 2) for t in gifs],
        "gif_median_s": round(statistics.median(gifs), 2),
        "gif_cpu_median_s": round(statistics.median(gif_cpu), 2),
        "load_average_1min": round(os.getloadavg()[0], 2),
        "gif_bytes": size,
        "png_median_s": round(statistics.median(pngs), 2),
    }


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Run, write the JSON and print it."""
    parser = argparse.ArgumentParser(
        prog="python -m bench.plot_speed",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--frames", type=int, default=60, help="frames of the animated clip")
    parser.add_argument("--repeat", type=int, default=3, help="timed runs of each")
    parser.add_argument("--out", type=Path, default=Path("runs/bench/plot_speed.json"))
    args = parser.parse_args(argv)
    result = run(args)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2))
    print(json.dumps(result, indent=2))
    return result


if __name__ == "__main__":
    main()
