"""bench.temporal_load's report: the roof, the loads, the cameras held and the people per frame, as Markdown
tables and JSON."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from bench.roof import RoofRow
from bench.stats import Result, fmt
from bench.temporal_roof import per_pose_roof
from bench.tracked import (
    FPS,
)

# Targets of issue 35 ("Fast path"), on the 2-core machine.
CAMERAS_TARGET = 32
P99_TARGET_MS = 25.0
PEOPLE_RATIO_TARGET = 3.0  # a 16-person frame's server CPU against a 1-person frame's
SATURATED_ROOF_TARGET = 0.8  # saturated tracked streams / both models' per-pose roof
WORKERS_TARGET = 1.6  # saturated tracked streams, the service's workers against one worker
CPU_PER_FRAME_CAMERAS = 8  # the camera count of the per-frame CPU targets
CPU_PER_FRAME_TARGET_MS = {True: 1.0, False: 0.6}  # tracked, untracked
HELD_FRACTION = 0.98  # of the offered frames, sent and answered within the window
EDGE_FRAMES = 1  # and beyond it, frames a camera may be short at the window's edges (phase, in flight)
PEOPLE_KINDS = {"untracked": "1 pose, untracked", "pose": "1 person (pose)", "1": "1 person (people)"}


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
    one_worker: list[Result] = field(default_factory=list)  # the saturated tracked load on --workers 1
    floor: list[Result] = field(default_factory=list)  # the transport's floor (bench.echo)
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

    def workers_ratio(self) -> float | None:
        """Saturated tracked frames/s of the service's workers against one worker's."""
        many = next((r for r in self.saturated if r.extra.get("tracked")), None)
        one = next(iter(self.one_worker), None)
        if many is None or one is None or not one.frames_per_s:
            return None
        return many.frames_per_s / one.frames_per_s

    def floor_of(self, load: str) -> Result | None:
        """The echo floor's result of one of bench.echo.FLOOR_LOADS (by the start of its name)."""
        return next((r for r in self.floor if r.name.startswith(f"(echo floor) {load}")), None)

    @property
    def targets(self) -> list[str]:
        """One line per target of issue 35 that this run measures: met or MISSED, with the figure."""
        lines = []
        verdict = {True: "met", False: "MISSED"}
        if self.searched:
            lines.append(
                f"{verdict[self.most_cameras >= CAMERAS_TARGET]}: causal temporal LiftStream holds "
                f"{self.most_cameras} cameras at {FPS:g} fps with p99 <= {self.p99_ms:g} ms "
                f"(target >= {CAMERAS_TARGET})"
            )
        for r in self.cameras:
            if r.concurrency == CPU_PER_FRAME_CAMERAS and (ms := cpu_ms_per_frame(r)) is not None:
                tracked = bool(r.extra.get("tracked"))
                target = CPU_PER_FRAME_TARGET_MS[tracked]
                floor = self.floor_of(f"{CPU_PER_FRAME_CAMERAS} cameras")
                beside = f"; the transport's floor {cpu_ms_per_frame(floor):.2f} ms" if floor else ""
                lines.append(
                    f"{verdict[ms <= target]}: server CPU per {'tracked' if tracked else 'untracked'} frame "
                    f"at {CPU_PER_FRAME_CAMERAS} paced cameras {ms:.2f} ms (target <= {target:g} ms{beside})"
                )
        best = self.roof_best["both"]
        for r in self.saturated:
            if r.extra.get("tracked") and best:
                ratio = r.frames_per_s / best
                floor = self.floor_of(f"{r.concurrency} streams")
                beside = f"; the transport's floor {floor.frames_per_s:,.0f} messages/s" if floor else ""
                lines.append(
                    f"{verdict[ratio >= SATURATED_ROOF_TARGET]}: saturated tracked streams "
                    f"{r.frames_per_s:,.0f} frames/s = {ratio:.2f} x both models' per-pose roof "
                    f"(target >= {SATURATED_ROOF_TARGET:g}{beside})"
                )
        if (workers := self.workers_ratio()) is not None:
            lines.append(
                f"{verdict[workers >= WORKERS_TARGET]}: saturated tracked streams, the service's workers / "
                f"one worker = {workers:.2f}x (target >= {WORKERS_TARGET:g}x)"
            )
        if ratio := self.people_ratio():
            lines.append(
                f"{verdict[ratio['server_cpu'] <= PEOPLE_RATIO_TARGET]}: a {self.people_count}-person frame "
                f"costs {ratio['server_cpu']:.2f}x a 1-person frame in server CPU ({ratio['p50']:.2f}x in "
                f"p50 latency, {ratio['p99']:.2f}x p99) (target <= {PEOPLE_RATIO_TARGET:g}x)"
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
                + loads_table(self.saturated + self.one_worker, best)
            )
        if self.cameras:
            parts.append(
                f"Cameras (paced at {FPS:g} fps each; held: p99 <= {self.p99_ms:g} ms, no errors, "
                f">= {HELD_FRACTION:.0%} of the offered frames answered, less {EDGE_FRAMES} a camera at "
                "the window's edges; measured in the order "
                f"{', '.join(map(str, self.searched))}):\n\n" + cameras_table(self.cameras)
            )
        if self.floor:
            parts.append(
                "The transport's floor (`bench.echo`: Python `grpc.aio` answering each frame with a fixed "
                "721-byte reply, no parsing, no model; the same clients):\n\n" + floor_table(self.floor)
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


def latency_cell(r: Result, key: str) -> str:
    """A latency percentile of a result, ms."""
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
            f"| {fmt(r.frames_per_s / best['both'], 3)} | {latency_cell(r, 'p50')} "
            f"| {latency_cell(r, 'p99')} | {r.errors} "
            f"| {fmt(r.server_cpu)} | {fmt(r.client_cpu)} | {fmt(r.extra.get('other_cpu'))} |"
        )
    return "\n".join(lines)


def cpu_ms_per_frame(r: Result) -> float | None:
    """Server CPU milliseconds per answered frame of a load."""
    if r.server_cpu is None or not r.frames_per_s:
        return None
    return 1000.0 * r.server_cpu / r.frames_per_s


def floor_table(results: list[Result]) -> str:
    """The echo server's loads: messages/s, latency and CPU per message."""
    lines = [
        "| load | messages/s | p50 ms | p99 ms | errors | server CPU | CPU ms per message |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in results:
        lines.append(
            f"| {r.name} | {fmt(r.frames_per_s, 0)} | {latency_cell(r, 'p50')} | {latency_cell(r, 'p99')} "
            f"| {r.errors} | {fmt(r.server_cpu)} | {fmt(cpu_ms_per_frame(r), 3)} |"
        )
    return "\n".join(lines)


def cameras_table(results: list[Result]) -> str:
    """One row per camera count: tracked and untracked side by side."""
    by: dict[int, dict[bool, Result]] = {}
    for r in results:
        by.setdefault(r.concurrency, {})[bool(r.extra.get("tracked"))] = r
    lines = [
        "| cameras | offered frames/s | tracked frames/s | p50 ms | p99 ms | errors | server CPU "
        "| CPU ms per frame | client CPU | other CPU | held | untracked frames/s | p50 ms | p99 ms "
        "| server CPU | CPU ms per frame |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|---:|---:|---:|---:|---:|",
    ]
    for n in sorted(by):
        t, u = by[n].get(True), by[n].get(False)
        row = [str(n), fmt(n * FPS, 0)]
        if t is not None:
            row += [fmt(t.frames_per_s, 0), latency_cell(t, "p50"), latency_cell(t, "p99"), str(t.errors)]
            row += [fmt(t.server_cpu), fmt(cpu_ms_per_frame(t))]
            row += [fmt(t.client_cpu), fmt(t.extra.get("other_cpu"))]
            row.append("yes" if t.extra.get("held") else "**no**")
        else:
            row += ["—"] * 9
        if u is not None:
            row += [fmt(u.frames_per_s, 0), latency_cell(u, "p50"), latency_cell(u, "p99"), fmt(u.server_cpu)]
            row.append(fmt(cpu_ms_per_frame(u)))
        else:
            row += ["—"] * 5
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
            f"| {latency_cell(r, 'p50')} | {latency_cell(r, 'p99')} "
            f"| {fmt(r.extra.get('server_cpu_ms_per_frame'))} "
            f"| {r.errors} |"
        )
    return "\n".join(lines)
