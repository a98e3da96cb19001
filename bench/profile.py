"""Profile the running service under one load with py-spy: where its CPU time goes, per thread and function.

    python -m bench.profile --load stream-x1 [--seconds 8] [--out runs/bench/profile-stream-x1.json]

Starts `python -m repnet serve` (or `--module bench.ceiling`) in a child process, samples it with
`py-spy record` (a dev dependency; it needs ptrace: root or CAP_SYS_PTRACE) while bench's own load
generator drives it, and prints the busiest threads and functions: *self* is time in the function's
own code, *inclusive* counts its callees too. Idle threads (waiting on a lock or on I/O) are not
sampled, so the shares are of the time the server's threads were running; with `--idle` they are
(py-spy --idle), and a thread that waits for the GIL shows where it waits: in the Python line it
cannot run, where a thread waiting for work shows in the wait itself (Condition.wait). Beside the
samples, each thread's CPU over the recording is read from /proc (every thread of the service and
its workers, onnxruntime's and gRPC's own included), in cores and in ms per frame of the load.
"""

from __future__ import annotations

import argparse
import logging
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

if __package__ in (None, ""):  # `python bench/profile.py`
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench.grpc_load import measure_stream, measure_unary
from bench.http_load import measure_http
from bench.server import CpuTimes, ServiceProcess, thread_cpu_seconds
from bench.stats import Result, write_json
from bench.temporal_load import measure_cameras, measure_people, measure_saturated

log = logging.getLogger("bench.profile")

LOADS: dict[str, Callable[[ServiceProcess, float], Result]] = {
    "http-c1": lambda s, d: measure_http("127.0.0.1", s.http_port, s.pid, 1, 1, d),
    "http-c8": lambda s, d: measure_http("127.0.0.1", s.http_port, s.pid, 1, 8, d),
    "http-batch256": lambda s, d: measure_http("127.0.0.1", s.http_port, s.pid, 256, 1, d),
    "grpc-c1": lambda s, d: measure_unary(s.target, s.pid, 1, 1, d),
    "stream-x1": lambda s, d: measure_stream(s.target, s.pid, 1, duration=d),
    "stream-x8": lambda s, d: measure_stream(s.target, s.pid, 8, duration=d),
    # causal temporal LiftStream (bench.temporal_load): paced tracked cameras, saturated tracked
    # streams, 16-person frames in lock-step
    "temporal-cameras-8": lambda s, d: measure_cameras(s, 8, True, _temporal_args(d)),
    "temporal-cameras-16": lambda s, d: measure_cameras(s, 16, True, _temporal_args(d)),
    "temporal-cameras-32": lambda s, d: measure_cameras(s, 32, True, _temporal_args(d)),
    "temporal-x8": lambda s, d: measure_saturated(s, 8, True, _temporal_args(d)),
    "temporal-people16": lambda s, d: measure_people(s, "16", _temporal_args(d)),
}


def _temporal_args(duration: float) -> argparse.Namespace:
    return argparse.Namespace(
        warmup=0.5, duration=duration, people_duration=duration, phase="spread", p99_ms=25.0
    )


@dataclass
class Profile:
    """Sample counts from py-spy's raw (collapsed stack) output."""

    samples: int = 0
    threads: Counter[str] = field(default_factory=Counter)
    self_time: Counter[str] = field(default_factory=Counter)
    inclusive: Counter[str] = field(default_factory=Counter)
    names: dict[int, str] = field(default_factory=dict)  # thread id -> its Python name

    @classmethod
    def parse(cls, text: str) -> Profile:
        """Lines `thread;frame;frame;... count`, outermost frame first."""
        profile = cls()
        for line in text.splitlines():
            stack, _, count = line.rpartition(" ")
            if not stack or not count.isdigit():
                continue
            n = int(count)
            thread, *frames = stack.split(";")
            profile.samples += n
            profile.threads[thread] += n
            for frame in [thread, *frames[:2]]:  # after the process (and the worker's) with --subprocesses
                if named := THREAD.fullmatch(frame):
                    profile.names[int(named[1])] = named[2]
            if frames:
                profile.self_time[frames[-1]] += n
                for frame in set(frames):
                    profile.inclusive[frame] += n
        return profile

    def table(self, counter: Counter[str], title: str, top: int) -> str:
        """The `top` entries of `counter` as a markdown table of shares."""
        lines = [f"| {title} | share of samples |", "|---|---:|"]
        for name, n in counter.most_common(top):
            lines.append(f"| `{name}` | {100 * n / max(self.samples, 1):.1f} % |")
        return "\n".join(lines)


THREAD = re.compile(r"thread \((\d+)\): (.*)")  # py-spy's --threads frame


def thread_table(
    before: CpuTimes,
    after: CpuTimes,
    seconds: float,
    per_s: float,
    names: dict[int, str],
) -> tuple[str, list[dict[str, Any]]]:
    """Each thread's CPU over the recording (cores) and per frame of the load (ms), busiest first;
    the name is Python's where py-spy saw the thread (onnxruntime's and gRPC's own threads have none)."""
    rows = []
    for tid, (pid, end) in after.items():
        cores = (end - before.get(tid, (pid, 0.0))[1]) / seconds
        if cores >= 0.005:
            rows.append({"thread": names.get(tid, "(not Python)"), "tid": tid, "pid": pid, "cores": cores})
    rows.sort(key=lambda r: -r["cores"])
    lines = ["| thread | process | CPU (cores) | ms per frame |", "|---|---:|---:|---:|"]
    for r in rows:
        r["ms_per_frame"] = 1e3 * r["cores"] / per_s if per_s else None
        per_frame = f"{r['ms_per_frame']:.3f}" if per_s else "-"
        lines.append(f"| `{r['thread']}` ({r['tid']}) | {r['pid']} | {r['cores']:.3f} | {per_frame} |")
    return "\n".join(lines), rows


Times = tuple[dict[int, tuple[int, float]], dict[int, tuple[int, float]], float]  # before, after, seconds


def record(
    service: ServiceProcess, load: str, seconds: float, rate: int, raw: Path, idle: bool = False
) -> tuple[Result, str, Times]:
    """Run py-spy on the service while the load runs (`idle`: idle threads sampled too); returns the
    load's Result, py-spy's output and every thread's CPU times at the recording's start and end
    (thread_cpu_seconds), with its length."""
    spy = shutil.which("py-spy") or str(Path(sys.executable).parent / "py-spy")
    command = [
        spy,
        "record",
        "--pid",
        str(service.pid),
        "--duration",
        str(int(seconds)),
        "--rate",
        str(rate),
        "--format",
        "raw",
        "--output",
        str(raw),
        "--nonblocking",
        "--threads",
        "--subprocesses",  # the workers (repnet serve --workers N), beside the supervisor
        *(["--idle"] if idle else []),
    ]
    result: list[Result] = []
    # The load starts first and runs 1 s longer than the recording, which starts once it is warm.
    runner = threading.Thread(target=lambda: result.append(LOADS[load](service, seconds + 1.5)))
    runner.start()
    time.sleep(1.0)
    before, start = thread_cpu_seconds(service.pid), time.monotonic()
    spy_run = subprocess.run(command, capture_output=True, text=True, check=False)
    times = (before, thread_cpu_seconds(service.pid), time.monotonic() - start)
    runner.join()
    if spy_run.returncode != 0 or not raw.exists():
        raise RuntimeError(f"py-spy failed ({spy_run.returncode}): {spy_run.stderr.strip()[-500:]}")
    return result[0], spy_run.stderr.strip(), times


def main(argv: list[str] | None = None) -> int:
    """Profile the service under one load with py-spy and print where the time went."""
    parser = argparse.ArgumentParser(
        prog="python -m bench.profile",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--load", choices=sorted(LOADS), required=True)
    parser.add_argument("--seconds", type=float, default=8.0, help="seconds recorded")
    parser.add_argument("--rate", type=int, default=200, help="samples per second")
    parser.add_argument("--module", default="repnet serve", help="'repnet serve' | bench.ceiling (no model)")
    parser.add_argument("--top", type=int, default=25, help="functions listed")
    parser.add_argument("--idle", action="store_true", help="sample idle threads too (py-spy --idle)")
    parser.add_argument("--service-flag", action="append", default=[], help="extra flag for the service")
    parser.add_argument("--out", type=Path, default=None, help="JSON summary (default: print only)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    with (
        tempfile.TemporaryDirectory() as tmp,
        ServiceProcess(*args.service_flag, module=args.module) as service,
    ):
        raw = Path(tmp) / "profile.txt"
        result, spy_log, (before, after, span) = record(
            service, args.load, args.seconds, args.rate, raw, args.idle
        )
        profile = Profile.parse(raw.read_text())
    threads, thread_rows = thread_table(before, after, span, result.frames_per_s, profile.names)
    log.info("%s", spy_log.splitlines()[-2] if spy_log else "")
    top = partial(profile.table, top=args.top)
    print(
        "\n\n".join(
            [
                f"`python -m bench.profile --load {args.load} --module {args.module}"
                f"{' --idle' if args.idle else ''}`: "
                f"{result.frames_per_s:,.0f} frames/s, p50 {result.latency_ms.get('p50', 0):.2f} ms, "
                f"server CPU {result.server_cpu or 0:.2f} cores, {profile.samples} samples",
                top(profile.threads, "thread"),
                "CPU per thread (/proc, over the recording; per frame of the load):\n\n" + threads,
                top(profile.self_time, "function (self)"),
                top(profile.inclusive, "function (inclusive)"),
            ]
        )
    )
    if args.out:
        write_json(
            args.out,
            {
                "load": args.load,
                "module": args.module,
                "idle": args.idle,
                "result": result,
                "samples": profile.samples,
                "thread_cpu": thread_rows,
                "threads": dict(profile.threads.most_common()),
                "self": dict(profile.self_time.most_common(200)),
                "inclusive": dict(profile.inclusive.most_common(200)),
            },
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
