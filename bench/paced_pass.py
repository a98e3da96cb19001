"""What one frame's work costs when frames come paced, against back to back: the models' batch-1 runs
and the service's whole pass (runtime.pipeline.run_jobs), each timed in thread CPU, with and without
an idle gap before each call.

    python -m bench.paced_pass [--gap-ms 8.3] [--calls 300] [--streams 32] [--out PATH.json]

A paced camera's frame finds the worker idle since the last one: 8 cameras at 30 fps on 2 workers
give a worker a frame every 8.3 ms. Back-to-back calls keep the weights, the interpreter's code and
data in the core's caches; after a gap, on a shared machine, part of them is gone. The gap is spent
asleep (the core idles) or spinning (the core stays busy with a loop that touches almost no memory);
each call's cost is its thread CPU time, the sleep or spin not counted. The last row is a saturated
run's pass: one tracked pose of each of --streams streams in one batch, its cost per pose. One
onnxruntime thread per session, as each of two workers has; the bundled single-frame and causal
models.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

if __package__ in (None, ""):  # `python bench/paced_pass.py`
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench.stats import machine, write_json
from bench.temporal_roof import clip_windows
from bench.tracked import FPS, moving_clip
from repnet.core.inputs import Limits, PoseInput
from repnet.runtime.lifter import Lifter
from repnet.runtime.pipeline import Job, StreamTracks, TrackedPose, run_jobs
from repnet.runtime.temporal import OUTPUT, TemporalLifter
from repnet.runtime.tracks import TrackBudget, TrackTable
from repnet.server.config import Settings
from repnet.server.startup import load_lifter


def _spin(seconds: float) -> None:
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        pass


GAPS: dict[str, Callable[[float], None]] = {"asleep": time.sleep, "spinning": _spin}


def thread_cpu_ms(call: Callable[[], Any], calls: int, gap_s: float, idle: Callable[[float], None]) -> float:
    """Mean thread CPU (ms) of `call`, each call after `gap_s` of `idle` (0: back to back)."""
    for _ in range(max(10, calls // 10)):  # warm up
        call()
    spent = 0.0
    for _ in range(calls):
        if gap_s:
            idle(gap_s)
        start = time.thread_time()
        call()
        spent += time.thread_time() - start
    return 1e3 * spent / calls


class Calls:
    """The calls timed: both models' batch-1 runs and the service's pass over one pose."""

    def __init__(self, lifter: Lifter, causal: TemporalLifter) -> None:
        self.lifter, self.causal = lifter, causal
        self.clip = moving_clip()
        self.limits = Limits()
        self.frame = 0
        self.budget = TrackBudget(1024)
        self.tracks = self.stream()
        slots = causal.contract.slots(FPS)  # a full window: the newest of a clip that long
        self.window = clip_windows(lifter, causal.contract, slots).slice(slots - 1, slots)
        self.pose_feed = {"keypoints_2d": self.clip[:1], "visibility": np.ones((1, 17), np.float32)}

    def single_run(self) -> None:
        """The single-frame model's session.run, batch 1."""
        self.lifter.session.run(None, self.pose_feed)

    def both_runs(self) -> None:
        """A tracked pose's two session.runs, batch 1."""
        self.single_run()
        self.causal.session.run([OUTPUT], self._window_feed())

    def _window_feed(self) -> dict[str, np.ndarray]:
        w = self.window
        return {"poses": w.poses, "keypoints_2d": w.keypoints_2d, "visibility": w.visibility, "fps": w.fps}

    def stream(self) -> StreamTracks:
        """A new stream's tracks."""
        return StreamTracks(TrackTable(self.causal.contract, 4, 60.0, self.budget), self.causal)

    def pass_of(self, tracked: bool, streams: int = 1) -> Callable[[], None]:
        """The service's pass over one frame of each of `streams` streams, one pose each (tracked:
        pushed into its stream's track and answered by the causal model too), replies built."""
        tracks = [self.tracks] if streams == 1 else [self.stream() for _ in range(streams)]

        def call() -> None:
            self.frame += 1
            points = self.clip[self.frame % len(self.clip)]
            spec = [TrackedPose("person", self.frame, FPS, "pose")] if tracked else []
            jobs = [
                Job(
                    finish=lambda lifted: lifted,
                    poses=[PoseInput(points, np.ones(17, bool), None, "h36m17", None)],
                    tracks=stream if tracked else None,
                    tracked=spec,
                )
                for stream in tracks
            ]
            run_jobs(self.lifter, jobs, self.limits, 256)

        return call


def measure(args: argparse.Namespace) -> dict[str, Any]:
    """Every call, back to back and after each gap, in turn."""
    settings = Settings(intra_op_threads=1)
    calls = Calls(load_lifter(settings), TemporalLifter.load(settings.causal_model_path, settings))
    timed = {
        "single-frame model, session.run batch 1": calls.single_run,
        "both models, session.run batch 1 each": calls.both_runs,
        "the service's pass, one untracked pose": calls.pass_of(False),
        "the service's pass, one tracked pose": calls.pass_of(True),
        f"the service's pass, {args.streams} streams' tracked poses, per pose": calls.pass_of(
            True, args.streams
        ),
    }
    rows = []
    for name, call in timed.items():
        per = args.streams if name.endswith("per pose") else 1  # a batch of that many poses a call
        count = max(10, args.calls // per)
        row: dict[str, Any] = {
            "call": name,
            "back_to_back_ms": thread_cpu_ms(call, count, 0.0, time.sleep) / per,
        }
        for idle_name, idle in GAPS.items():
            row[f"{idle_name}_ms"] = thread_cpu_ms(call, count, args.gap_ms / 1e3, idle) / per
        rows.append(row)
        print(_line(row, args.gap_ms), flush=True)
    return {
        "when": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "machine": machine(),
        "gap_ms": args.gap_ms,
        "calls": args.calls,
        "rows": rows,
    }


def _line(row: dict[str, Any], gap_ms: float) -> str:
    base = row["back_to_back_ms"]
    after = " | ".join(f"{row[f'{n}_ms']:.3f} ({row[f'{n}_ms'] / base:.2f}x)" for n in GAPS)
    return f"| {row['call']} | {base:.3f} | {after} |"


def main(argv: list[str] | None = None) -> int:
    """Measure, print the table and write the JSON."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--gap-ms", type=float, default=1e3 / (4 * FPS), help="idle before each call (ms)")
    parser.add_argument("--calls", type=int, default=300, help="calls timed per row and gap")
    parser.add_argument("--streams", type=int, default=32, help="streams of the last row's batch")
    parser.add_argument("--out", type=Path, default=Path("runs/bench/paced_pass.json"))
    args = parser.parse_args(argv)
    gaps = " | ".join(f"after {args.gap_ms:.1f} ms {n}" for n in GAPS)
    print(f"| ms thread CPU a call | back to back | {gaps} |\n|---|---:|---:|---:|", flush=True)
    write_json(args.out, measure(args))
    return 0


if __name__ == "__main__":
    sys.exit(main())
