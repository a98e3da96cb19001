"""The temporal models' graph as stored against as served (runtime.rewrite: strided convolutions as
matrix products, broadcasts over short trailing axes tiled): CPU time per pose by batch, and the
largest difference of their answers.

    python -m bench.rewrite [--batches 1 8 16 64] [--rounds 5] [--out runs/bench/rewrite.json]

One onnxruntime thread each, the two sessions timed in turn, round after round (the best round of
each kept), on the same windows of 49 frames at 30 fps.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import onnxruntime as ort

if __package__ in (None, ""):  # `python bench/rewrite.py`
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench.stats import write_json
from repnet.runtime.loading import BUNDLED_CAUSAL, BUNDLED_OFFLINE
from repnet.runtime.session import SessionOptions, open_session, read_model


def windows(n: int, slots: int, seed: int) -> dict[str, np.ndarray]:
    """n windows of `slots` frames: a pose (mm) drifting, its 2D, nearly every joint visible."""
    rng = np.random.default_rng(seed)
    poses = (rng.normal(0, 300, (n, 1, 17, 3)) + rng.normal(0, 20, (n, slots, 17, 3))).astype(np.float32)
    return {
        "poses": poses,
        "keypoints_2d": (poses[..., :2] * 0.5 + 500).astype(np.float32),
        "visibility": (rng.random((n, slots, 17)) > 0.1).astype(np.float32),
        "fps": np.full(n, 30.0, np.float32),
    }


def cpu_ms_per_pose(session: ort.InferenceSession, feeds: dict[str, np.ndarray], runs: int) -> float:
    """CPU time of this thread per pose over `runs` runs (ms)."""
    start = time.thread_time()
    for _ in range(runs):
        session.run(None, feeds)
    return (time.thread_time() - start) / runs / len(feeds["fps"]) * 1e3


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Time both graphs of both temporal models; print and return the table."""
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 8, 16, 64])
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args(argv)
    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    options.inter_op_num_threads = 1
    options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    result: dict[str, Any] = {}
    for mode, path in (("causal", BUNDLED_CAUSAL), ("offline", BUNDLED_OFFLINE)):
        stored = ort.InferenceSession(read_model(path), options, providers=["CPUExecutionProvider"])
        served = open_session(path, SessionOptions(intra_op_threads=1))
        worst = 0.0
        rows = []
        for batch in args.batches:
            feeds = windows(batch, 49, seed=batch)
            worst = max(worst, float(np.abs(stored.run(None, feeds)[0] - served.run(None, feeds)[0]).max()))
            runs = max(20, 1600 // batch)
            best = {"stored": float("inf"), "served": float("inf")}
            for _ in range(args.rounds):
                for name, session in (("stored", stored), ("served", served)):
                    best[name] = min(best[name], cpu_ms_per_pose(session, feeds, runs))
            rows.append({"batch": batch, **best, "speedup": best["stored"] / best["served"]})
            print(
                f"{mode:8} batch {batch:4}: {best['stored']:.3f} -> {best['served']:.3f} ms CPU a pose "
                f"({best['stored'] / best['served']:.2f}x)",
                flush=True,
            )
        print(f"{mode:8} largest answer difference: {worst:.2g} mm")
        result[mode] = {"rows": rows, "max_diff_mm": worst}
    if args.out:
        write_json(args.out, result)
    return result


if __name__ == "__main__":
    main()
