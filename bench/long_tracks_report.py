"""bench.long_tracks' report: the run summarised against its targets, as JSON and Markdown."""

from __future__ import annotations

import argparse
import sys
from datetime import datetime, timezone
from typing import Any

from bench.stats import machine
from bench.tracked import (
    load_average,
)

GROWTH_LIMIT = 0.05  # the most RSS may grow after the warm-up, as a share of it


def summarize(run: dict[str, Any], args: argparse.Namespace) -> dict[str, Any]:
    """Memory growth after the warm-up, the open tracks along the way and at the end."""
    samples = run.pop("samples")
    idle, end = samples[0], samples[-1]
    warm = next((s for s in samples if s["frames"] >= args.warmup), end)
    during = samples[1:-1] or samples
    return {
        "command": " ".join(["python -m bench.long_tracks", *sys.argv[1:]]),
        "when": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "machine": machine(),
        "settings": {
            k: getattr(args, k)
            for k in ("tracks", "lanes", "people", "track_frames", "drop", "track_idle_s", "warmup", "window")
        },
        **run,
        "frames_per_s": run["frames"] / run["seconds"],
        "rss_mb": {
            "idle_start": idle["rss_mb"],
            "after_warmup": warm["rss_mb"],
            "end": end["rss_mb"],
            "peak": max(s["rss_mb"] for s in samples),
        },
        "open_tracks": {
            "min": min(s.get("open_tracks", 0) for s in during),
            "max": max(s.get("open_tracks", 0) for s in during),
            "end": end.get("open_tracks"),
            "end_bytes": end.get("track_state_bytes"),
        },
        "growth_after_warmup": (end["rss_mb"] - warm["rss_mb"]) / warm["rss_mb"],
        "growth_from_idle": (end["rss_mb"] - idle["rss_mb"]) / idle["rss_mb"],
        "warmed_up": warm is not end,
        "load_average_end": load_average(),
        "samples": samples,
    }


def markdown(result: dict[str, Any]) -> str:
    """The result as markdown, against the growth limit."""
    rss, tracks, s = result["rss_mb"], result["open_tracks"], result["settings"]
    freed = tracks["end"] == 0 and tracks["end_bytes"] == 0
    ok = result["growth_after_warmup"] < GROWTH_LIMIT and result["bad_answers"] == 0 and freed
    ok = ok and result["warmed_up"]
    rows = "\n".join(
        f"| {x['frames']:,} | {x['seconds']:,.0f} | {x['rss_mb']:.1f} | {x.get('open_tracks', 0):.0f} |"
        for x in result["samples"]
    )
    return (
        f"`{result['command']}` on {result['machine']['cpus']} CPUs ({result['machine']['cpu']}), "
        f"{result['when']}: {result['frames']:,} tracked frames, {s['tracks']} tracks open at a time on "
        f"{s['lanes']} lanes ({s['people']} per LiftFrame), each track {s['track_frames']} frames "
        f"(dropped by: {s['drop']}; REPNET_TRACK_IDLE_S {s['track_idle_s']:g}), "
        f"{result['tracks_opened']:,} tracks and {result['streams_opened']:,} streams opened in "
        f"{result['seconds']:,.0f} s ({result['frames_per_s']:,.0f} frames/s, server CPU "
        f"{result['server_cpu']:.2f} cores), {result['bad_answers']} bad answers; load average "
        f"{result['load_average_end']:.2f} at the end.\n\n"
        f"| server RSS | MB |\n|---|---:|\n| idle at start | {rss['idle_start']:.1f} |\n"
        f"| after warm-up | {rss['after_warmup']:.1f} |\n| peak | {rss['peak']:.1f} |\n"
        f"| end | {rss['end']:.1f} |\n\n"
        f"Open tracks during the run {tracks['min']:.0f}–{tracks['max']:.0f}; at the end (every stream "
        f"closed) {tracks['end']:.0f} tracks holding {tracks['end_bytes']:.0f} bytes.\n\n"
        f"| frames | s | RSS MB | open tracks |\n|---:|---:|---:|---:|\n{rows}\n\n"
        f"Growth after warm-up {100 * result['growth_after_warmup']:+.2f} % "
        f"(from idle {100 * result['growth_from_idle']:+.2f} %): "
        f"{'met' if ok else 'MISSED'} (target < {100 * GROWTH_LIMIT:.0f} %, no bad answers, every "
        f"track freed at the end)."
    )
