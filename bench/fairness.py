"""Fairness between clients: what a paced camera, a one-pose HTTP client and the probes see while
another client floods the service.

    python -m bench.fairness                        # each phase 15 s, default settings
    python -m bench.fairness --flood-streams 8 --people 16 --duration 10 --out runs/bench/fairness.json

Phases, each against the same fresh `repnet serve`:
- quiet: no flood;
- flood: a flooder in a process of its own opens --flood-streams LiftStreams (a connection each) of
  --people tracked people per frame at 30 fps of stream time, sent as fast as the server reads them
  (256 frames in flight each, so the server's stream window is what holds them back).

Meanwhile the victims: --cameras LiftStreams paced at 30 fps with one tracked person each (cameras,
a connection each: with several workers, the kernel spreads connections over them), one client
sending POST /lift of one pose every 20 ms on a keep-alive connection, and a prober asking GET
/readyz on a fresh connection and gRPC health every 0.25 s. Prints per phase the cameras' and the
HTTP client's p50/p99, the worst probes and the flooder's frames/s; it measures, it asserts
nothing. Targets (issue 30): the camera's p99 <= 100 ms, HTTP p99 <= 100 ms, /readyz <= 0.5 s.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import multiprocessing
import sys
import threading
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

if __package__ in (None, ""):  # `python bench/fairness.py`
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench.server import ServiceProcess
from bench.slow_clients import Seen, _normal_client, _probe, summary
from bench.stats import fmt, latency_summary, machine, write_json
from bench.temporal_clients import camera, crowd_frames, run_id, run_streams
from bench.tracked import FPS

log = logging.getLogger("bench.fairness")

TARGET_MS = {"camera p99": 100.0, "HTTP p99": 100.0, "/readyz": 500.0}


def flooder(target: str, pid: int, streams: int, people: int, seconds: float, out: Any) -> None:
    """The flooding client (its own process): `streams` streams of `people`-person frames."""
    rid = f"flood{run_id()}"
    sources = [crowd_frames(people, f"{rid}s{k}") for k in range(streams)]
    tally = asyncio.run(run_streams(target, pid, sources, fps=0, window=256, warmup=0.5, duration=seconds))
    out.put({"frames": tally.completed, "errors": tally.errors, "seconds": seconds})


def phase(service: ServiceProcess, flood: bool, args: argparse.Namespace) -> dict[str, Any]:
    """One phase: the victims for args.duration seconds, with or without the flood."""
    context = multiprocessing.get_context("spawn")
    results = context.Queue()
    process = None
    if flood:
        process = context.Process(
            target=flooder,
            args=(
                service.target,
                service.pid,
                args.flood_streams,
                args.people,
                args.warmup + args.duration,
                results,
            ),
            daemon=True,
        )
        process.start()
        time.sleep(args.warmup + 0.5)  # the flood is on before the victims are measured
    seen = Seen()
    stop = time.monotonic() + args.duration
    prober = threading.Thread(target=_probe, args=(service, stop, seen), daemon=True)
    prober.start()

    async def victims() -> Any:
        rid = run_id()
        cam = run_streams(
            service.target, service.pid, [camera(k, True, rid) for k in range(args.cameras)], fps=FPS,
            window=256, warmup=0.0, duration=args.duration,
        )  # fmt: skip
        tally, _ = await asyncio.gather(cam, _normal_client("127.0.0.1", service.http_port, stop, seen))
        return tally

    tally = asyncio.run(victims())
    prober.join(timeout=10)
    found = summary(seen)
    found["camera_ms"] = latency_summary(tally.latencies)
    found["camera_errors"] = tally.errors
    found["camera_frames"] = tally.completed
    if process is not None:
        process.join(timeout=args.duration + 60)
        flood_seen = results.get(timeout=10) if not results.empty() else {}
        found["flood_frames_per_s"] = flood_seen.get("frames", 0) / max(flood_seen.get("seconds", 1), 1e-9)
        found["flood_errors"] = flood_seen.get("errors")
        if process.is_alive():
            process.kill()
    return found


def report(rows: dict[str, dict[str, Any]]) -> str:
    """A markdown table, one row per phase, then the targets."""
    lines = [
        "| phase | camera p50 / p99 ms (errors) | HTTP /lift p50 / p99 ms | HTTP statuses | worst /readyz ms "
        "(failed) | worst health ms | flood frames/s (errors) |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, r in rows.items():
        cam, http = r["camera_ms"], r["lift_ms"]
        lines.append(
            f"| {name} | {fmt(cam.get('p50'))} / {fmt(cam.get('p99'))} ({r['camera_errors']}) "
            f"| {fmt(http.get('p50'))} / {fmt(http.get('p99'))} | {r['lift_statuses']} "
            f"| {fmt(r['readyz_worst_ms'], 1)} ({r['readyz_failed']}) | {fmt(r['health_worst_ms'], 1)} "
            f"| {fmt(r.get('flood_frames_per_s'), 0)} ({r.get('flood_errors', '—')}) |"
        )
    flood = rows.get("flood")
    if flood:
        seen = {
            "camera p99": flood["camera_ms"].get("p99"),
            "HTTP p99": flood["lift_ms"].get("p99"),
            "/readyz": flood["readyz_worst_ms"],
        }
        for name, target in TARGET_MS.items():
            value = seen[name]
            ok = value is not None and value <= target and not flood["camera_errors"]
            verdict = "met" if ok else "MISSED"
            lines.append(f"\n- {verdict}: {name} under the flood {fmt(value)} ms (target <= {target:g})")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Run the phases and print the table."""
    parser = argparse.ArgumentParser(prog="python -m bench.fairness", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    parser.add_argument("--flood-streams", type=int, default=8)
    parser.add_argument("--cameras", type=int, default=4, help="victim cameras (a connection each)")
    parser.add_argument("--people", type=int, default=16, help="tracked people per flood frame")
    parser.add_argument("--duration", type=float, default=15.0, help="seconds measured per phase")
    parser.add_argument("--warmup", type=float, default=2.0)
    parser.add_argument("--service-flag", action="append", default=[], help="extra flag for the service")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    logging.getLogger("httpx").setLevel(logging.WARNING)
    rows = {}
    with ServiceProcess(*args.service_flag) as service:
        for name, flood in (("quiet", False), ("flood", True)):
            log.info("phase %s", name)
            rows[name] = phase(service, flood, args)
    when = datetime.now(timezone.utc).isoformat(timespec="seconds")
    print(f"`python -m bench.fairness {' '.join(sys.argv[1:])}`, {when}, {machine()['cpus']} CPUs; "
          f"flood: {args.flood_streams} streams of {args.people} tracked people; victims: {args.cameras} "
          f"cameras\n")  # fmt: skip
    print(report(rows))
    if args.out:
        write_json(args.out, {"when": when, "argv": sys.argv[1:], "machine": machine(), "phases": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
