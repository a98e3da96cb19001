"""Optional int8 dynamic quantization of the model, and its speed and output change against float32.

    python -m bench.quantize [--model PATH] [--out runs/bench/repnet-h36m-int8.onnx]

Weights of MatMul/Gemm become int8 (onnxruntime.quantization.quantize_dynamic); activations are
quantized per run. The ONNX metadata is kept, with "-int8" added to model_id. Serve it with
`python -m repnet serve --model-path OUT`; measure Protocol II with
`python -m repnet.train.evaluate --model OUT --frame-step 10 --table-frame-step 0`.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path
from typing import Any

import numpy as np

if __package__ in (None, ""):  # `python bench/quantize.py`
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench.roof import measure_roof
from bench.stats import sample_poses, write_json
from repnet.core import geometry
from repnet.runtime.lifter import Lifter
from repnet.runtime.loading import BUNDLED_MODEL
from repnet.server.config import Settings

log = logging.getLogger("bench.quantize")


def quantize(model: Path, out: Path) -> Path:
    """int8 dynamic quantization of `model` into `out`, metadata kept and model_id marked."""
    import onnx  # build-time tools, not service dependencies
    from onnxruntime.quantization import QuantType, quantize_dynamic

    out.parent.mkdir(parents=True, exist_ok=True)
    quantize_dynamic(model, out, weight_type=QuantType.QInt8)
    quantized = onnx.load(str(out))
    meta = {p.key: p.value for p in quantized.metadata_props if p.key != "onnx.infer"}
    meta["model_id"] = f"{meta.get('model_id', model.stem)}-int8"
    meta["quantization"] = "onnxruntime quantize_dynamic, int8 weights (QInt8), from " + model.name
    del quantized.metadata_props[:]
    onnx.helper.set_model_props(quantized, meta)
    onnx.save(quantized, str(out))
    return out


def output_change(float_model: Path, int8_model: Path, n: int = 4096) -> dict[str, float]:
    """How far int8 outputs move from float32 ones on plausible poses (mm after root alignment)."""
    points = sample_poses(n, seed=7)
    visible = np.ones(points.shape[:2], np.float32)
    a, b = (Lifter.load(m).lift(points, visible) for m in (float_model, int8_model))  # no start-up check
    joint = np.linalg.norm(a.pose_3d - b.pose_3d, axis=-1)  # (n, 17)
    reprojection = [geometry.reproject(p.camera, p.pose_3d, points, visible) for p in (a, b)]
    return {
        "pose_3d_mean_mm": float(joint.mean()),
        "pose_3d_p99_mm": float(np.percentile(joint, 99)),
        "reprojection_mean_px": float(np.abs(reprojection[0] - reprojection[1]).mean()),
    }


def compare(float_model: Path, int8_model: Path, duration: float) -> dict[str, Any]:
    """The roof of the float32 and the int8 model, and how far their outputs move apart."""
    rows = {}
    for name, path in (("float32", float_model), ("int8", int8_model)):
        roof = measure_roof(Settings(model_path=path), duration=duration, with_lifter=False)
        rows[name] = {r.batch: {"frames_per_s": r.frames_per_s, "ms_per_call": r.ms_per_call} for r in roof}
    return {
        "float_model": str(float_model),
        "int8_model": str(int8_model),
        "size_mb": {"float32": float_model.stat().st_size / 2**20, "int8": int8_model.stat().st_size / 2**20},
        "roof": rows,
        "output_change": output_change(float_model, int8_model),
    }


def markdown(result: dict[str, Any]) -> str:
    """The comparison as markdown."""
    roof = result["roof"]
    lines = [
        "| batch | float32 frames/s | int8 frames/s | speed-up | float32 ms | int8 ms |",
        "|---:|---:|---:|---:|---:|---:|",
    ]
    for batch in roof["float32"]:
        f, q = roof["float32"][batch], roof["int8"][batch]
        lines.append(
            f"| {batch} | {f['frames_per_s']:,.0f} | {q['frames_per_s']:,.0f} | "
            f"{q['frames_per_s'] / f['frames_per_s']:.2f}× | {f['ms_per_call']:.3f} | "
            f"{q['ms_per_call']:.3f} |"
        )
    change = result["output_change"]
    size = result["size_mb"]
    lines.append(
        f"\nSize {size['float32']:.1f} MB -> {size['int8']:.1f} MB. int8 moves pose_3d by "
        f"{change['pose_3d_mean_mm']:.2f} mm per joint on average (p99 {change['pose_3d_p99_mm']:.2f} mm)."
    )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Quantize the model, compare it with the original, print and write the result."""
    parser = argparse.ArgumentParser(
        prog="python -m bench.quantize",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--model", type=Path, default=BUNDLED_MODEL)
    parser.add_argument("--out", type=Path, default=Path("runs/bench/repnet-h36m-int8.onnx"))
    parser.add_argument("--duration", type=float, default=2.0, help="seconds per roof batch size")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    quantize(args.model, args.out)
    result = compare(args.model, args.out, args.duration)
    result["command"] = " ".join(["python -m bench.quantize", *sys.argv[1:]])
    write_json(args.out.with_suffix(".json"), result)
    print(markdown(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
