"""Capacity and cost of causal temporal lifting on gRPC LiftStream, and the temporal model's roof.

    python -m bench.temporal_load [--cameras 8,16,32,48,64] [--duration 10] [--out PATH.json]

1. The roof: raw onnxruntime runs of the causal temporal model (the service's session settings) on
   windows of K slots for 30 fps (temporal.Contract.slots), built from a tracked person's
   single-frame answers, at each batch size; the single-frame model's session.run at the same
   sizes; and both per tracked pose (a tracked pose costs one run of each).
2. Saturated streams: S LiftStreams of one tracked person each (track_id, fps 30, a moving pose,
   frame ids increasing), 256 frames in flight each; then the same streams untracked.
3. Cameras: N LiftStreams paced at 30 frames/s each, one tracked person per frame, their send times
   spread evenly over a frame period; then the same N streams untracked. N is searched: the
   --cameras counts in turn until one is not held, then halved down to --refine cameras between the
   last held and the first not. Held: p99 <= --p99-ms per frame, no errors, and >= 98 % of the
   offered frames sent and answered within the window.
4. People per frame: one stream in lock-step (one frame in flight) of 1-person frames (`pose`),
   1-person frames (`people`) and --people-person frames (`people`): per-frame latency and server
   CPU, and their ratio (target: a 16-person frame < 4x a 1-person frame).

The service runs as `python -m service` in a child process with the same flags as the roof's
session; the load generator is this process, on the same machine. Each load's CPU (server, this
client, everything else on the machine) is measured over its window, with the load average.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import grpc
import httpx
import numpy as np

if __package__ in (None, ""):  # `python bench/temporal_load.py`
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench.grpc_load import LIFT_STREAM, OPTIONS
from bench.roof import RoofRow, measure_roof, time_calls
from bench.server import ServiceProcess, rss_bytes
from bench.stats import Result, fmt, latency_summary, machine, write_json
from bench.tracked import (
    FPS,
    Check,
    Crowd,
    Load,
    drive,
    expect_people,
    expect_pose,
    load_average,
    moving_clip,
    pose_parts,
    result_of,
    single_frame,
    watch,
)
from service.app import load_lifter, parse_settings
from service.config import Settings
from service.lifter import Lifter
from service.temporal import OUTPUT, Contract, TemporalLifter, Windows
from service.tracking import camera_poses
from service.tracks import Observation, Track, track_capacity

log = logging.getLogger("bench.temporal_load")

# Targets of issue 21 ("Capacity and cost").
CAMERAS_TARGET = 64
P99_TARGET_MS = 25.0
PEOPLE_RATIO_TARGET = 4.0
HELD_FRACTION = 0.98  # of the offered frames, sent and answered within the window
ROOF_BATCHES = (1, 8, 64, 256)
DEFAULT_MAX_STREAMS = 64  # REPNET_GRPC_MAX_STREAMS' default


# --- the roof -------------------------------------------------------------------------------


def clip_windows(lifter: Lifter, contract: Contract, count: int, fps: float = FPS) -> Windows:
    """The causal windows of `count` consecutive frames of one tracked person (a moving clip lifted
    by the single-frame model, pushed into a Track as a stream pushes it)."""
    points = moving_clip(count)
    visible = np.ones(points.shape[:2], bool)
    prediction = lifter.lift(points, visible)
    poses = camera_poses(prediction, np.arange(count))
    track = Track(track_capacity(contract, fps), fps)
    windows = []
    for frame in range(count):
        track.push(frame, Observation(poses[frame], points[frame], np.ones(17, np.float32)))
        windows.append(track.window(contract))
    return Windows.join(windows, causal=True)


def temporal_roof(
    settings: Settings, batches: tuple[int, ...], duration: float
) -> tuple[list[RoofRow], Contract]:
    """Raw onnxruntime runs of the causal model (the service's session settings) at each batch size,
    on real windows at 30 fps; with the single-frame model's session.run at the same sizes."""
    rows = measure_roof(settings, batches, duration, with_lifter=False)
    temporal = TemporalLifter.load(settings.causal_model_path, settings)
    windows = clip_windows(load_lifter(settings), temporal.contract, max(batches))
    for batch in batches:
        part = windows.slice(0, batch)
        feeds = {
            "poses": part.poses,
            "keypoints_2d": part.keypoints_2d,
            "visibility": part.visibility,
            "fps": part.fps,
        }

        def run(feeds: dict[str, np.ndarray] = feeds) -> None:
            temporal.session.run([OUTPUT], feeds)

        calls, seconds, laps = time_calls(run, duration)
        rows.append(RoofRow("temporal session.run", batch, calls, seconds, latency_summary(laps)))
    return rows, temporal.contract


def per_pose_roof(rows: list[RoofRow]) -> dict[int, dict[str, float]]:
    """Per batch size: frames/s of the single-frame model, of the temporal model, and of both per
    tracked pose (1 / (1/a + 1/b): a tracked pose costs one run of each)."""
    out: dict[int, dict[str, float]] = {}
    for r in rows:
        model = "temporal" if r.what.startswith("temporal") else "single"
        out.setdefault(r.batch, {})[model] = r.frames_per_s
    for values in out.values():
        if "temporal" in values and "single" in values:
            values["both"] = 1 / (1 / values["single"] + 1 / values["temporal"])
    return out


# --- loads ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class Source:
    """What one stream sends: frame_of(n), how answers are checked, the people per frame."""

    frame_of: Callable[[int], bytes]
    check: Check
    people: int = 1


def camera(index: int, tracked: bool, run_id: str) -> Source:
    """One camera's frames: a person (moving as person `index`) tracked at 30 fps, or untracked."""
    parts = pose_parts(moving_clip(seed=index))
    track_id = f"cam{index}-{run_id}" if tracked else ""
    return Source(lambda n: single_frame(parts, n, track_id), expect_pose(temporal=tracked))


def crowd_frames(people: int, run_id: str) -> Source:
    """Frames of `people` tracked people (LiftFrame.people) at 30 fps."""
    crowd = Crowd.of(people)
    ids = [f"p{k}-{run_id}" for k in range(people)]
    return Source(lambda n: crowd.frame(n, ids), expect_people(people), people)


async def run_streams(
    target: str,
    server_pid: int,
    sources: list[Source],
    *,
    fps: float,
    window: int,
    warmup: float,
    duration: float,
    spread: bool = True,
) -> Load:
    """One LiftStream per source, paced at `fps` (0: flooding, `window` frames in flight), measured
    for `duration` seconds after `warmup`; paced streams' send times are spread evenly over one
    frame period (`spread`) or all at once."""
    async with grpc.aio.insecure_channel(target, options=OPTIONS) as channel:
        open_stream: grpc.aio.StreamStreamMultiCallable[bytes, bytes] = channel.stream_stream(LIFT_STREAM)
        start = time.perf_counter() + warmup
        tally = Load(start, start + duration)
        calls = [open_stream(timeout=warmup + duration + 60) for _ in sources]
        step = 1 / (fps * len(sources)) if fps and spread else 0.0
        await asyncio.gather(
            watch(server_pid, tally),
            *(
                drive(call, s.frame_of, tally, s.check, fps=fps, window=window, phase_s=k * step)
                for k, (call, s) in enumerate(zip(calls, sources, strict=True))
            ),
        )
    return tally


_runs = 0


def run_id() -> str:
    """A new suffix for track ids: every load starts its tracks afresh."""
    global _runs
    _runs += 1
    return f"r{_runs}"


def measure_cameras(service: ServiceProcess, count: int, tracked: bool, args: argparse.Namespace) -> Result:
    """`count` cameras at 30 fps, one person each, tracked or not."""
    rid = run_id()
    sources = [camera(k, tracked, rid) for k in range(count)]
    tally = asyncio.run(
        run_streams(
            service.target, service.pid, sources, fps=FPS, window=256, warmup=args.warmup,
            duration=args.duration, spread=args.phase == "spread",
        )
    )  # fmt: skip
    name = f"{count} cameras at {FPS:g} fps, " + ("tracked" if tracked else "untracked")
    result = result_of(name, count, 1, tally, offered=count * FPS * args.duration, tracked=tracked)
    result.extra["held"] = held(result, args.p99_ms)
    return result


def held(result: Result, p99_ms: float) -> bool:
    """The cameras were served: p99 within the target, no errors, the offered frames sent and answered."""
    offered = result.extra["offered"]
    return (
        result.errors == 0
        and result.latency_ms.get("p99", float("inf")) <= p99_ms
        and result.extra["sent"] >= HELD_FRACTION * offered
        and result.calls >= HELD_FRACTION * offered
    )


def search(counts: list[int], is_held: Callable[[int], bool], refine: int) -> tuple[int, list[int]]:
    """The most cameras held: `counts` ascending until one is not held, then the gap between the
    last held and the first not halved down to `refine` cameras (0: no halving). Returns it (0 when
    none is held) and the counts in the order they were measured."""
    tried: list[int] = []
    best, failed = 0, None
    for n in sorted(counts):
        tried.append(n)
        if not is_held(n):
            failed = n
            break
        best = n
    while failed is not None and refine and failed - best > refine:
        n = (best + failed) // 2
        tried.append(n)
        if is_held(n):
            best = n
        else:
            failed = n
    return best, tried


def measure_saturated(
    service: ServiceProcess, streams: int, tracked: bool, args: argparse.Namespace
) -> Result:
    """`streams` streams of one person each, 256 frames in flight: throughput."""
    rid = run_id()
    sources = [camera(k, tracked, rid) for k in range(streams)]
    tally = asyncio.run(
        run_streams(
            service.target, service.pid, sources, fps=0, window=256, warmup=args.warmup,
            duration=args.duration,
        )
    )  # fmt: skip
    name = f"LiftStream x{streams}, 256 in flight, " + ("tracked" if tracked else "untracked")
    return result_of(name, streams, 1, tally, tracked=tracked)


def measure_people(service: ServiceProcess, kind: str, args: argparse.Namespace) -> Result:
    """One stream in lock-step (one frame in flight) of one kind of frame (see PEOPLE_KINDS)."""
    rid = run_id()
    if kind == "pose":
        source = camera(0, True, rid)
    elif kind == "untracked":
        source = camera(0, False, rid)
    else:
        source = crowd_frames(int(kind), rid)
    tally = asyncio.run(
        run_streams(
            service.target, service.pid, [source], fps=0, window=1, warmup=args.warmup,
            duration=args.people_duration,
        )
    )  # fmt: skip
    result = result_of(PEOPLE_KINDS.get(kind, f"{kind} people (people)"), 1, 1, tally, people=source.people)
    cpu = tally.cpu.get("server", 0.0)
    result.extra["server_cpu_ms_per_frame"] = 1e3 * cpu / max(result.calls, 1)
    return result


PEOPLE_KINDS = {"untracked": "1 pose, untracked", "pose": "1 person (pose)", "1": "1 person (people)"}


# --- the report -----------------------------------------------------------------------------


@dataclass
class Report:
    """Everything one run measured; written as JSON and printed as markdown."""

    when: str
    command: str
    machine: dict[str, Any]
    models: dict[str, str]
    contract: dict[str, Any]
    service_flags: list[str]
    roof: list[RoofRow]
    saturated: list[Result] = field(default_factory=list)
    cameras: list[Result] = field(default_factory=list)
    most_cameras: int = 0
    searched: list[int] = field(default_factory=list)
    people: list[Result] = field(default_factory=list)
    people_count: int = 16
    server_rss_mb: dict[str, float] = field(default_factory=dict)
    load_average: dict[str, float] = field(default_factory=dict)
    roof_end: list[RoofRow] = field(default_factory=list)
    p99_ms: float = P99_TARGET_MS
    wall_s: float = 0.0

    def roof_per_pose(self) -> dict[int, dict[str, float]]:
        """Per batch size, the better of the two roof passes (see per_pose_roof)."""
        best: dict[int, dict[str, float]] = {}
        for rows in (self.roof, self.roof_end):
            for batch, values in per_pose_roof(rows).items():
                for key, value in values.items():
                    best.setdefault(batch, {})[key] = max(value, best.get(batch, {}).get(key, 0.0))
        return best

    @property
    def roof_best(self) -> dict[str, float]:
        """The best frames/s over the batch sizes: single-frame, temporal, both per tracked pose."""
        per = self.roof_per_pose().values()
        return {k: max((v.get(k, 0.0) for v in per), default=0.0) for k in ("single", "temporal", "both")}

    def people_ratio(self) -> dict[str, float]:
        """A many-person frame against a 1-person (`pose`) frame: server CPU per frame, p50, p99."""
        by = {r.extra.get("people"): r for r in self.people if r.name != PEOPLE_KINDS["untracked"]}
        one = next((r for r in self.people if r.name == PEOPLE_KINDS["pose"]), None)
        many = by.get(self.people_count)
        if one is None or many is None or not one.latency_ms or not many.latency_ms:
            return {}
        cpu1, cpu_n = one.extra["server_cpu_ms_per_frame"], many.extra["server_cpu_ms_per_frame"]
        return {
            "server_cpu": cpu_n / cpu1 if cpu1 else float("inf"),
            "p50": many.latency_ms["p50"] / one.latency_ms["p50"],
            "p99": many.latency_ms["p99"] / one.latency_ms["p99"],
        }

    @property
    def targets(self) -> list[str]:
        """One line per target of issue 21 that this run measures: met or MISSED, with the figure."""
        lines = []
        if self.searched:
            ok = self.most_cameras >= CAMERAS_TARGET
            lines.append(
                f"{'met' if ok else 'MISSED'}: causal temporal LiftStream holds {self.most_cameras} cameras "
                f"at {FPS:g} fps with p99 <= {self.p99_ms:g} ms (target >= {CAMERAS_TARGET})"
            )
        if ratio := self.people_ratio():
            worst = max(ratio["server_cpu"], ratio["p50"])
            ok = worst < PEOPLE_RATIO_TARGET
            lines.append(
                f"{'met' if ok else 'MISSED'}: a {self.people_count}-person frame costs "
                f"{ratio['server_cpu']:.2f}x a 1-person frame in server CPU, {ratio['p50']:.2f}x in p50 "
                f"latency ({ratio['p99']:.2f}x p99) (target < {PEOPLE_RATIO_TARGET:g}x)"
            )
        return lines

    def markdown(self) -> str:
        """The whole report as markdown."""
        load = self.load_average
        parts = [
            f"`{self.command}` on {self.machine['cpus']} CPUs ({self.machine['cpu']}), {self.when}, "
            f"models {self.models.get('single')} + {self.models.get('causal')} (causal, "
            f"K = {self.contract.get('slots_30fps')} slots at {FPS:g} fps), service flags "
            f"`{' '.join(self.service_flags)}`; load average {load.get('start', 0):.2f} at the start, "
            f"{load.get('end', 0):.2f} at the end; run took {self.wall_s:.0f} s.",
            "Roof (raw onnxruntime, frames/s; the better of the passes before and after the loads):\n\n"
            + roof_table(self.roof_per_pose()),
        ]
        best = self.roof_best
        if self.saturated:
            parts.append(
                "Saturated streams (one person per stream, 256 frames in flight each):\n\n"
                + loads_table(self.saturated, best)
            )
        if self.cameras:
            parts.append(
                f"Cameras (paced at {FPS:g} fps each; held: p99 <= {self.p99_ms:g} ms, no errors, "
                f">= {HELD_FRACTION:.0%} of the offered frames answered; measured in the order "
                f"{', '.join(map(str, self.searched))}):\n\n" + cameras_table(self.cameras)
            )
        if self.people:
            parts.append(
                "People per frame (one stream, one frame in flight):\n\n" + people_table(self.people)
            )
        parts.append("\n".join(f"- {line}" for line in self.targets))
        rss = self.server_rss_mb
        if rss:
            parts.append(f"Server RSS {rss['start']:.1f} MB after start, {rss['end']:.1f} MB at the end.")
        return "\n\n".join(parts)


def roof_table(per: dict[int, dict[str, float]]) -> str:
    """Roof frames/s per batch size."""
    lines = [
        "| batch | single-frame session.run | temporal session.run | both, per tracked pose |",
        "|---:|---:|---:|---:|",
    ]
    for batch in sorted(per):
        v = per[batch]
        lines.append(
            f"| {batch} | {fmt(v.get('single'), 0)} | {fmt(v.get('temporal'), 0)} | {fmt(v.get('both'), 0)} |"
        )
    return "\n".join(lines)


def _lat(r: Result, key: str) -> str:
    return fmt(r.latency_ms.get(key))


def loads_table(results: list[Result], best: dict[str, float]) -> str:
    """Throughput against the roofs."""
    lines = [
        "| load | frames/s | × temporal roof | × both roof | p50 ms | p99 ms | errors | server CPU "
        "| client CPU | other CPU |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in results:
        lines.append(
            f"| {r.name} | {fmt(r.frames_per_s, 0)} | {fmt(r.frames_per_s / best['temporal'], 3)} "
            f"| {fmt(r.frames_per_s / best['both'], 3)} | {_lat(r, 'p50')} | {_lat(r, 'p99')} | {r.errors} "
            f"| {fmt(r.server_cpu)} | {fmt(r.client_cpu)} | {fmt(r.extra.get('other_cpu'))} |"
        )
    return "\n".join(lines)


def cameras_table(results: list[Result]) -> str:
    """One row per camera count: tracked and untracked side by side."""
    by: dict[int, dict[bool, Result]] = {}
    for r in results:
        by.setdefault(r.concurrency, {})[bool(r.extra.get("tracked"))] = r
    lines = [
        "| cameras | offered frames/s | tracked frames/s | p50 ms | p99 ms | errors | server CPU "
        "| client CPU | other CPU | held | untracked frames/s | p50 ms | p99 ms | server CPU |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|---:|---:|---:|---:|",
    ]
    for n in sorted(by):
        t, u = by[n].get(True), by[n].get(False)
        row = [str(n), fmt(n * FPS, 0)]
        if t is not None:
            row += [fmt(t.frames_per_s, 0), _lat(t, "p50"), _lat(t, "p99"), str(t.errors)]
            row += [fmt(t.server_cpu), fmt(t.client_cpu), fmt(t.extra.get("other_cpu"))]
            row.append("yes" if t.extra.get("held") else "**no**")
        else:
            row += ["—"] * 8
        if u is not None:
            row += [fmt(u.frames_per_s, 0), _lat(u, "p50"), _lat(u, "p99"), fmt(u.server_cpu)]
        else:
            row += ["—"] * 4
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines)


def people_table(results: list[Result]) -> str:
    """Per-frame cost of frames with 1 and many people."""
    lines = [
        "| frame | people | frames/s | people/s | p50 ms | p99 ms | server CPU ms per frame | errors |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in results:
        people = int(r.extra.get("people", 1))
        lines.append(
            f"| {r.name} | {people} | {fmt(r.frames_per_s, 0)} | {fmt(r.frames_per_s * people, 0)} "
            f"| {_lat(r, 'p50')} | {_lat(r, 'p99')} | {fmt(r.extra.get('server_cpu_ms_per_frame'))} "
            f"| {r.errors} |"
        )
    return "\n".join(lines)


# --- the run --------------------------------------------------------------------------------


def service_flags(args: argparse.Namespace) -> list[str]:
    """The service's flags: --service-flag values, and room for the cameras when more than the
    default stream limit are asked for (unless a --grpc-max-streams is given)."""
    flags = list(args.service_flag)
    most = max([*args.cameras, args.streams])
    if most > DEFAULT_MAX_STREAMS and not any(f.startswith("--grpc-max-streams") for f in flags):
        flags.append(f"--grpc-max-streams={most}")
    return flags


def run(args: argparse.Namespace) -> Report:
    """The roof, the loads against a fresh service, the roof again."""
    flags = service_flags(args)
    settings = parse_settings(flags)
    started, load_start = time.perf_counter(), load_average()
    log.info("roof (load average %.2f)", load_start)
    roof, contract = temporal_roof(settings, args.batches, args.roof_duration)
    report = Report(
        when=datetime.now(timezone.utc).isoformat(timespec="seconds"),
        command=" ".join(["python -m bench.temporal_load", *sys.argv[1:]]),
        machine=machine(),
        models={"single": settings.model_path.name, "causal": settings.causal_model_path.name},
        contract={**contract.__dict__, "slots_30fps": contract.slots(FPS)},
        service_flags=flags or ["(defaults)"],
        roof=roof,
        people_count=args.people,
        p99_ms=args.p99_ms,
    )
    with ServiceProcess(*flags) as service:
        rss_start = rss_bytes(service.pid)
        ready = httpx.get(f"{service.url}/readyz", timeout=10).json()
        report.models["single_id"] = str(ready.get("model_id"))
        measure_loads(service, args, report)
        report.server_rss_mb = {"start": rss_start / 2**20, "end": rss_bytes(service.pid) / 2**20}
    log.info("roof again, after the loads")
    report.roof_end, _ = temporal_roof(settings, args.batches, args.roof_duration)
    report.load_average = {"start": load_start, "end": load_average()}
    report.wall_s = time.perf_counter() - started
    return report


def measure_loads(service: ServiceProcess, args: argparse.Namespace, report: Report) -> None:
    """The saturated streams, the camera search and the people per frame, into the report."""
    if args.streams:
        for tracked in (True, False):
            log.info("saturated: %d streams, tracked=%s", args.streams, tracked)
            report.saturated.append(measure_saturated(service, args.streams, tracked, args))

    def is_held(count: int) -> bool:
        log.info("cameras: %d, tracked", count)
        result = measure_cameras(service, count, True, args)
        report.cameras.append(result)
        log.info("  p99 %.1f ms, %s", result.latency_ms.get("p99", float("nan")), result.extra["held"])
        if args.untracked:
            log.info("cameras: %d, untracked", count)
            report.cameras.append(measure_cameras(service, count, False, args))
        return bool(result.extra["held"])

    if args.cameras:
        report.most_cameras, report.searched = search(args.cameras, is_held, args.refine)
    for kind in ("untracked", "pose", "1", str(args.people)) if args.people else ():
        log.info("people per frame: %s", kind)
        report.people.append(measure_people(service, kind, args))


def _ints(text: str) -> list[int]:
    return [int(v) for v in text.split(",") if v.strip()]


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line of `python -m bench.temporal_load`."""
    parser = argparse.ArgumentParser(
        prog="python -m bench.temporal_load",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--cameras", type=_ints, default=[8, 16, 32, 48, 64, 80, 96],
                        help="camera counts to try, ascending (empty: skip the search)")  # fmt: skip
    parser.add_argument("--refine", type=int, default=4, help="halve the gap after the search down to this")
    parser.add_argument("--p99-ms", type=float, default=P99_TARGET_MS, help="held: p99 per frame <= this")
    parser.add_argument("--phase", choices=("spread", "sync"), default="spread",
                        help="cameras send spread evenly over a frame period, or all at once")  # fmt: skip
    parser.add_argument("--no-untracked", dest="untracked", action="store_false",
                        help="skip the untracked run beside each camera count")  # fmt: skip
    parser.add_argument("--streams", type=int, default=8, help="saturated streams (0: skip)")
    parser.add_argument("--people", type=int, default=16, help="people of the many-person frame (0: skip)")
    parser.add_argument("--duration", type=float, default=10.0, help="seconds measured per load")
    parser.add_argument("--people-duration", type=float, default=5.0, help="seconds per people load")
    parser.add_argument("--warmup", type=float, default=2.0, help="seconds before each measured window")
    parser.add_argument("--batches", type=lambda t: tuple(_ints(t)), default=ROOF_BATCHES)
    parser.add_argument("--roof-duration", type=float, default=1.5, help="seconds per roof batch size")
    parser.add_argument("--service-flag", action="append", default=[],
                        help="extra flag for `python -m service` (and the roof's sessions)")  # fmt: skip
    parser.add_argument("--out", type=Path, default=Path("runs/bench/temporal_load.json"))
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark, print the markdown and write the JSON; the exit status."""
    args = parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    report = run(args)
    write_json(args.out, report)
    print(report.markdown())
    log.info("wrote %s", args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
