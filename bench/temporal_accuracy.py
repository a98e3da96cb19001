"""Temporal accuracy through the service: the held-out tails of the training subjects, sent to
POST /lift as each client would (Stacked-Hourglass detections as mpii16, the projected truth as
h36m17), each clip one track, with temporal off, causal and offline.

python -m bench.temporal_accuracy --out runs/bench/temporal_accuracy.json

Sets: sh25, the detections at their 25 Hz; sh50, detections and truth upsampled to 50 Hz
(Catmull-Rom); gt25, the projected truth at 25 Hz. Figures per set and mode, over every frame:
acceleration error and MPJVE (mm / frame^2 and mm / frame at the clip's own rate), P-II and P-I
(pose_3d_camera against the camera-frame truth, root-aligned, mm), and the std of each limb bone's
length within a clip (mm, mean over clips and bones). Validation data only: never S9/S11.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np
from fastapi.testclient import TestClient
from prometheus_client import CollectorRegistry

from repnet.runtime.loading import BUNDLED_CAUSAL, BUNDLED_MODEL, BUNDLED_OFFLINE
from repnet.server.app import build_app, build_batcher, load_lifter, load_temporal
from repnet.server.config import Settings
from repnet.server.metrics import Metrics
from repnet.train import data, sequences
from repnet.train.temporal_data import figures

MODES = ("off", "causal", "offline")
KINDS = ("sh25", "sh50", "gt25")


def clip_request(clip: sequences.ValidationClip, mode: str) -> dict[str, Any]:
    """The POST /lift body of one clip: one track, every frame, the clip's own format."""
    poses = [
        {
            "keypoints": [None if np.isnan(p).any() else p.tolist() for p in frame],
            "track_id": "clip",
            "frame": f,
        }
        for f, frame in enumerate(clip.source)
    ]
    return {"poses": poses, "format": clip.source_format, "temporal": mode, "fps": clip.fps}


def run(settings: Settings, data_dir: Path, kinds: tuple[str, ...], modes: tuple[str, ...]) -> dict[str, Any]:
    """Every set through every mode; {set: {mode: figures}}."""
    lifter = load_lifter(settings)
    registry = Metrics(CollectorRegistry())
    temporal = load_temporal(settings, lifter, registry)
    engine = build_batcher(lifter, registry, settings)
    results: dict[str, Any] = {}
    try:
        with TestClient(
            build_app(engine, registry, settings, temporal), base_url="http://localhost"
        ) as client:
            for kind in kinds:
                clips = sequences.validation_clips(data_dir, kind)
                results[kind] = {}
                for mode in modes:
                    started = time.monotonic()
                    answers = []
                    for clip in clips:
                        response = client.post("/lift", json=clip_request(clip, mode))
                        if response.status_code != 200:
                            raise RuntimeError(
                                f"{clip.name} {mode}: {response.status_code} {response.text[:300]}"
                            )
                        pose = np.array([p["pose_3d_camera"] for p in response.json()["poses"]], np.float64)
                        answers.append((pose, clip.truth.astype(np.float64)))
                    results[kind][mode] = figures(answers) | {"seconds": round(time.monotonic() - started, 1)}
                    print(
                        kind,
                        mode,
                        json.dumps({k: round(v, 2) for k, v in results[kind][mode].items()}),
                        flush=True,
                    )
    finally:
        engine.close(10)
        for temporal_engine in temporal.engines.values() if temporal is not None else ():
            temporal_engine.close(10)
    return results


def table(results: dict[str, Any]) -> str:
    """A Markdown table of the results."""
    lines = [
        "| set | mode | accel mm/frame² | MPJVE mm/frame | P-II mm | P-I mm | limb bone std mm |",
        "|---|---|---:|---:|---:|---:|---:|",
    ]
    for kind, modes in results.items():
        for mode, f in modes.items():
            lines.append(
                f"| {kind} | {mode} | {f['accel']:.2f} | {f['mpjve']:.2f} | {f['pa_mpjpe']:.1f} | "
                f"{f['mpjpe']:.1f} | {f['bone_std']:.2f} |"
            )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    """python -m bench.temporal_accuracy: print the table, write the JSON."""
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--data-dir", default="", help="Human3.6M folder (default: $REPNET_H36M_DIR, ../shared)"
    )
    parser.add_argument(
        "--model",
        type=Path,
        default=BUNDLED_MODEL,
        help="the single-frame model the temporal models run over (default: the bundled one; an "
        "adapted model of it, `repnet adapt`, keeps its temporal models)",
    )
    parser.add_argument("--causal-model", type=Path, default=BUNDLED_CAUSAL)
    parser.add_argument("--offline-model", type=Path, default=BUNDLED_OFFLINE)
    parser.add_argument("--kinds", nargs="+", default=list(KINDS), choices=KINDS)
    parser.add_argument("--modes", nargs="+", default=list(MODES), choices=MODES)
    parser.add_argument("--threads", type=int, default=1, help="onnxruntime threads per run")
    parser.add_argument("--out", type=Path, help="write the figures as JSON here")
    args = parser.parse_args(argv)
    settings = Settings(
        model_path=args.model,
        intra_op_threads=args.threads,
        causal_model_path=args.causal_model,
        offline_model_path=args.offline_model,
        max_temporal_poses=8192,  # the longest held-out clip at 50 Hz has 1,500 frames
        queue_size=8192,
    )
    results = run(
        settings, data.resolve_data_dir(args.data_dir or None), tuple(args.kinds), tuple(args.modes)
    )
    print(table(results))
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(results, indent=1) + "\n")


if __name__ == "__main__":
    main()
