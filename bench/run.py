"""One benchmark run: the raw-model roof, then HTTP and gRPC against `repnet serve` in a child process.

    python -m bench.run [--model PATH] [--duration 3] [--out runs/bench/bench.json]

The roof is measured first, alone on the machine; then the service starts on free localhost
ports with the same thread settings and is loaded from this process (its own GIL). Then the
same service without the model (bench.ceiling) takes the loads whose targets are ratios, which
shows what the transports alone reach on the machine, and bench.echo's bare HTTP server (uvicorn and
httptools, no app code) the single-pose HTTP load: the HTTP floor. Last, the roof is measured again:
ratios use the better of the two passes.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import datetime, timezone
from functools import partial
from pathlib import Path
from typing import Any

import httpx

if __package__ in (None, ""):  # `python bench/run.py`
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench.grpc_load import measure_stream, measure_unary
from bench.http_load import measure_http
from bench.roof import BATCHES, RoofRow, measure_roof, roof_table
from bench.server import ServiceProcess, rss_bytes
from bench.stats import Result, fmt, machine, results_table, write_json
from repnet.server.app import parse_settings

log = logging.getLogger("bench")

# Targets of the benchmark issue.
STREAM_FRACTION_OF_ROOF = 0.7
HTTP_P50_MS, HTTP_P99_MS = 3.0, 10.0


def service_loads(
    service: ServiceProcess, duration: float, quick: bool
) -> list[tuple[str, Callable[[], Result]]]:
    """The measured configurations, in order."""
    pid, host, port, target = service.pid, "127.0.0.1", service.http_port, service.target
    loads: list[tuple[str, Callable[[], Result]]] = []
    for c in (1, 8) if quick else (1, 8, 64):
        loads.append((f"http c{c}", partial(measure_http, host, port, pid, 1, c, duration)))
    for c in (1,) if quick else (1, 4):
        loads.append((f"http batch256 c{c}", partial(measure_http, host, port, pid, 256, c, duration)))
    for c in (1, 8):
        loads.append((f"grpc unary c{c}", partial(measure_unary, target, pid, 1, c, duration)))
    loads.append(("grpc unary batch256 c1", partial(measure_unary, target, pid, 256, 1, duration)))
    loads.append(("stream lock-step", partial(measure_stream, target, pid, 1, window=1, duration=duration)))
    for s in (1, 8):
        loads.append((f"stream x{s}", partial(measure_stream, target, pid, s, duration=duration)))
    loads.append(("stream x8 @ 50 fps", partial(measure_stream, target, pid, 8, duration=duration, fps=50)))
    return loads


CEILING = "(no model) "  # name prefix of the rows measured against bench.ceiling
CEILING_LOADS = ("http c1", "stream x1", "stream x8")  # of service_loads: those whose targets are ratios
FLOOR = "(http floor) "  # the row of HTTP c1 against bench.echo: uvicorn and httptools, no app code


@dataclass
class Report:
    """Everything one run measured; written as JSON and printed as markdown."""

    when: str
    command: str
    machine: dict[str, Any]
    model: str
    model_id: str  # as the running service reports it (/readyz)
    service_flags: list[str]
    intra_op_threads: int
    roof: list[RoofRow]  # measured before the service loads
    results: list[Result]
    server_rss_mb: dict[str, float]
    wall_s: float = 0.0
    roof_end: list[RoofRow] = field(default_factory=list)  # measured again after them

    def _roof_rows(self, batch: int | None = None) -> list[RoofRow]:
        return [
            r
            for r in (*self.roof, *self.roof_end)
            if r.what == "session.run" and (batch is None or r.batch == batch)
        ]

    @property
    def roof_best(self) -> float:
        """The roof's best batched throughput, frames/s (session.run alone), over both roof passes:
        a busy moment on a shared machine during one pass must not flatter the service's ratios."""
        return max(r.frames_per_s for r in self._roof_rows())

    @property
    def roof_batch1_ms(self) -> float:
        """The faster of the two passes' batch-1 calls, ms."""
        return min(r.ms_per_call for r in self._roof_rows(batch=1))

    @property
    def targets(self) -> list[str]:
        """One line per target of the issue: met or missed, with the figure."""
        lines = []
        ceiling = {(r.name, r.concurrency): r for r in self.results if r.name.startswith(CEILING)}
        for r in self.results:
            if (
                r.name.startswith("gRPC LiftStream")
                and r.name.endswith("in flight")
                and "1 frame" not in r.name
            ):
                ratio = r.frames_per_s / self.roof_best
                ok = ratio >= STREAM_FRACTION_OF_ROOF
                line = (
                    f"{'met' if ok else 'MISSED'}: LiftStream x{r.concurrency} at {ratio:.2f} of the "
                    f"roof (target >= {STREAM_FRACTION_OF_ROOF})"
                )
                if bare := ceiling.get((CEILING + r.name, r.concurrency)):
                    line += (
                        f"; without the model the same load reaches {bare.frames_per_s / self.roof_best:.2f}"
                    )
                lines.append(line)
            if r.name == "HTTP /lift, 1 pose" and r.concurrency == 1:
                p50, p99 = r.latency_ms["p50"], r.latency_ms["p99"]
                ok = p50 <= HTTP_P50_MS and p99 <= HTTP_P99_MS
                line = (
                    f"{'met' if ok else 'MISSED'}: HTTP single pose c1 p50 {p50:.2f} ms, p99 {p99:.2f} ms "
                    f"(targets <= {HTTP_P50_MS}, <= {HTTP_P99_MS}); p50 minus the roof's batch-1 call: "
                    f"{p50 - self.roof_batch1_ms:.2f} ms"
                )
                if bare := ceiling.get((CEILING + r.name, r.concurrency)):
                    line += f"; without the model p50 {bare.latency_ms['p50']:.2f} ms"
                if floor := next((f for f in self.results if f.name == FLOOR + r.name), None):
                    line += f"; the HTTP floor (uvicorn, no app code) p50 {floor.latency_ms['p50']:.2f} ms"
                lines.append(line)
        return lines

    def markdown(self) -> str:
        """The whole report as markdown."""
        rss = self.server_rss_mb
        return "\n\n".join(
            [
                f"`{self.command}` on {self.machine['cpus']} CPUs ({self.machine['cpu']}), {self.when}, "
                f"model `{Path(self.model).name}` ({self.model_id}), "
                f"service flags `{' '.join(self.service_flags)}`",
                "Roof before the service loads:\n\n" + roof_table(self.roof),
                *(["Roof after them:\n\n" + roof_table(self.roof_end)] if self.roof_end else []),
                f"Roof best (both passes): {self.roof_best:,.0f} frames/s; batch 1: "
                f"{self.roof_batch1_ms:.3f} ms per call.",
                results_table(self.results, self.roof_best),
                "\n".join(f"- {line}" for line in self.targets),
                f"Server RSS {fmt(rss['start'], 1)} MB after start, {fmt(rss['end'], 1)} MB at the end; "
                f"run took {self.wall_s:.0f} s.",
            ]
        )


def run(args: argparse.Namespace) -> Report:
    """The roof, the service loads, the ceiling and the roof again."""
    flags = [*(["--model-path", str(args.model)] if args.model else []), *args.service_flag]
    settings = parse_settings(flags)  # what the service will run with, REPNET_* variables included
    started = time.perf_counter()
    log.info("roof: %s, intra-op threads %d", settings.model_path.name, settings.intra_op_threads)
    roof = measure_roof(settings, BATCHES, args.roof_duration)
    results: list[Result] = []
    with ServiceProcess(*flags) as service:
        rss_start = rss_bytes(service.pid)
        model_id = str(httpx.get(f"{service.url}/readyz", timeout=10).json()["model_id"])
        for label, load in service_loads(service, args.duration, args.quick):
            log.info("measuring %s", label)
            results.append(load())
        rss_end = rss_bytes(service.pid)
    if not args.no_ceiling:
        with ServiceProcess(*flags, module="bench.ceiling") as bare:
            for label, load in service_loads(bare, args.duration, args.quick):
                if label not in CEILING_LOADS:
                    continue
                log.info("measuring %s without the model", label)
                result = load()
                result.name = CEILING + result.name
                results.append(result)
    if not args.no_ceiling:
        with ServiceProcess(module="bench.echo") as echo:
            log.info("measuring http c1 against the HTTP floor (bench.echo)")
            result = measure_http("127.0.0.1", echo.http_port, echo.pid, 1, 1, args.duration)
            result.name = FLOOR + result.name
            results.append(result)
    log.info("roof again, after the service loads")
    roof_end = measure_roof(settings, BATCHES, args.roof_duration)
    return Report(
        when=datetime.now(timezone.utc).isoformat(timespec="seconds"),
        command=" ".join(["python -m bench.run", *sys.argv[1:]]),
        machine=machine(),
        model=str(settings.model_path),
        model_id=model_id,
        service_flags=flags or ["(defaults)"],
        intra_op_threads=settings.intra_op_threads,
        roof=roof,
        roof_end=roof_end,
        results=results,
        server_rss_mb={"start": rss_start / 2**20, "end": rss_end / 2**20},
        wall_s=time.perf_counter() - started,
    )


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line of `python -m bench.run`."""
    parser = argparse.ArgumentParser(
        prog="python -m bench.run", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--model", type=Path, default=None, help="ONNX model (default: the bundled one)")
    parser.add_argument("--duration", type=float, default=3.0, help="seconds measured per service load")
    parser.add_argument("--roof-duration", type=float, default=2.0, help="seconds per roof batch size")
    parser.add_argument("--quick", action="store_true", help="fewer configurations (a smoke run)")
    parser.add_argument(
        "--no-ceiling",
        action="store_true",
        help="skip the service without the model (bench.ceiling) and the HTTP floor (bench.echo)",
    )
    parser.add_argument(
        "--service-flag",
        action="append",
        default=[],
        help="extra flag for `python -m repnet serve`, e.g. --service-flag=--max-wait-ms=1",
    )
    parser.add_argument("--out", type=Path, default=Path("runs/bench/bench.json"), help="JSON results")
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
