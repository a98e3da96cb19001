"""The `repnet` command: serve, lift files of poses (via the service or locally), plot, list formats."""

from __future__ import annotations

import argparse
import importlib
import json
import os
import re
import sys
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar, cast

import numpy as np

from service.client import DEFAULT_URL, LiftClient, LiftClientError, LiftResult
from service.errors import ModelLoadError
from service.formats import FORMATS, MODEL_PARENTS, format_table

# Exit codes: 0 done; 1 the service or model rejected the input; 2 bad usage, input file or model
# file; 3 the service could not be reached.
EXIT_OK, EXIT_REJECTED, EXIT_USAGE, EXIT_UNREACHABLE = 0, 1, 2, 3
T = TypeVar("T")
Lift = Callable[[np.ndarray, "np.ndarray | None"], list[LiftResult]]


class InputFileError(Exception):
    """The input file cannot be read as poses."""


@dataclass(frozen=True)
class Poses:
    """Poses read from a file."""

    points: np.ndarray  # (N, J, 2) px, NaN where a joint is missing
    confidence: np.ndarray | None  # (N, J) in [0, 1], or None
    format: str | None  # the format the file names, if any


def _pose_array(rows: Any, where: str) -> np.ndarray:
    """One pose of J rows ([x, y], [x, y, c] or null) -> (J, 3): NaN rows for null, c NaN if not given."""
    if not isinstance(rows, list) or not rows:
        raise InputFileError(f"{where}: expected a non-empty list of joints, got {type(rows).__name__}")
    out = np.full((len(rows), 3), np.nan)
    for j, row in enumerate(rows):
        if row is None:
            continue
        numbers = isinstance(row, list) and all(isinstance(v, int | float) for v in row)
        if not numbers or len(row) not in (2, 3):
            raise InputFileError(f"{where}[{j}]: expected [x, y], [x, y, confidence] or null, got {row!r}")
        out[j, : len(row)] = row
    return out


def _stack(poses: Sequence[np.ndarray], confidence: Any, fmt: Any, where: str) -> Poses:
    """(J, 3) poses from _pose_array, with `confidence` (N, J) overriding their third column."""
    if not poses:
        raise InputFileError(f"{where}: no poses")
    if len({p.shape for p in poses}) != 1:
        raise InputFileError(f"{where}: poses have different joint counts {sorted({len(p) for p in poses})}")
    data = np.stack(poses)  # (N, J, 3)
    if confidence is None and not np.isnan(data[..., 2]).all():
        confidence = np.nan_to_num(data[..., 2], nan=1.0)  # a joint given without confidence counts as sure
    conf = None if confidence is None else np.asarray(confidence, dtype=np.float64).reshape(data.shape[:2])
    return Poses(data[..., :2], conf, None if fmt is None else str(fmt))


def _read_json(data: Any) -> Poses:
    if isinstance(data, dict) and "people" in data:  # OpenPose --write_json: x, y, c triples, 0 = missing
        people = [np.asarray(p["pose_keypoints_2d"], dtype=np.float64).reshape(-1, 3) for p in data["people"]]
        people = [np.where(p[:, 2:] > 0, p, np.nan) for p in people]
        return _stack(people, None, "body25" if people and len(people[0]) == 25 else None, "people")
    if isinstance(data, dict) and "poses" in data:  # the POST /lift body
        items = data["poses"] if isinstance(data["poses"], list) else []
        poses = [_pose_array(p.get("keypoints") if isinstance(p, dict) else None, f"poses[{i}].keypoints")
                 for i, p in enumerate(items)]  # fmt: skip
        for pose, item in zip(poses, items, strict=True):
            if isinstance(item, dict) and item.get("confidence") is not None:
                pose[:, 2] = np.asarray(item["confidence"], dtype=np.float64)
        return _stack(poses, None, data.get("format"), "poses")
    body = data if isinstance(data, dict) else {"keypoints": data}
    keypoints, fmt = body.get("keypoints"), body.get("format")
    many = isinstance(keypoints, list) and bool(keypoints) and isinstance(keypoints[0], list) and \
        any(isinstance(row, list) for row in keypoints[0])  # fmt: skip
    rows: list[Any] = keypoints if many and isinstance(keypoints, list) else [keypoints]
    arrays = [_pose_array(r, f"keypoints[{i}]") for i, r in enumerate(rows)]
    return _stack(arrays, body.get("confidence"), fmt, "keypoints")


def load_poses(path: Path) -> Poses:
    """Poses from a .json (a pose, a list of poses, a POST /lift body or OpenPose output) or .npz
    (`keypoints` (N, J, 2|3) or (J, 2|3) with NaN for missing joints, optional `confidence`, `format`)."""
    try:
        if path.suffix == ".npz":
            with np.load(path, allow_pickle=False) as npz:
                if "keypoints" not in npz:
                    raise InputFileError(f"{path}: no 'keypoints' array (has {', '.join(npz.files)})")
                keypoints = np.asarray(npz["keypoints"], dtype=np.float64)
                conf = npz["confidence"] if "confidence" in npz else None
                fmt = npz["format"] if "format" in npz else None
            keypoints = keypoints[None] if keypoints.ndim == 2 else keypoints
            if keypoints.ndim != 3 or keypoints.shape[-1] not in (2, 3):
                raise InputFileError(f"expected keypoints (N, J, 2) or (N, J, 3), got {keypoints.shape}")
            padded = np.pad(keypoints, ((0, 0), (0, 0), (0, 3 - keypoints.shape[-1])), constant_values=np.nan)
            return _stack(list(padded), conf, fmt, str(path))
        if path.suffix == ".json":
            return _read_json(json.loads(path.read_text()))
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as err:
        raise InputFileError(f"{path}: {err}") from err
    raise InputFileError(f"{path}: expected a .json or .npz file")


def _shift_pose_indices(message: str, offset: int) -> str:
    """Rename poses[i] to poses[offset + i] in a message about one chunk of the file."""
    return re.sub(r"poses\[(\d+)\]", lambda m: f"poses[{offset + int(m.group(1))}]", message)


def _progress(items: Sequence[T], total: int, enabled: bool) -> Iterable[T]:
    try:
        tqdm = importlib.import_module("tqdm").tqdm
    except ImportError:  # progress bars are optional: pip install 'repnet[cli]'
        return items
    bar = tqdm(items, total=total, unit="batch", disable=None if enabled else True, file=sys.stderr)
    return cast(Iterable[T], bar)


def _remote_lift(url: str, fmt: str, threshold: float | None, timeout: float) -> tuple[Lift, LiftClient]:
    client = LiftClient(url, timeout=timeout)

    def lift(points: np.ndarray, conf: np.ndarray | None) -> list[LiftResult]:
        return client.lift_batch(points, format=fmt, confidence=conf, confidence_threshold=threshold)

    return lift, client


def _local_lift(model: Path | None, fmt: str, threshold: float | None, batch: int) -> Lift:
    """Lift in this process with the service's own code: load checks, input rules, response fields."""
    from service.__main__ import limits_of, load_lifter
    from service.config import BUNDLED_MODEL, Settings
    from service.errors import LiftError
    from service.http_api import to_pose_results
    from service.keypoints import PoseInput, prepare_poses

    settings = Settings(
        model_path=model or BUNDLED_MODEL, max_request_poses=batch, queue_size=max(batch, 4096)
    )
    lifter, limits = load_lifter(settings), limits_of(settings)
    joints, model_id = lifter.info.joint_names, lifter.info.model_id

    def lift(points: np.ndarray, conf: np.ndarray | None) -> list[LiftResult]:
        poses = [PoseInput(p, ~np.isnan(p).any(axis=1), None if conf is None else conf[i], fmt)
                 for i, p in enumerate(points)]  # fmt: skip
        try:
            inputs = prepare_poses(poses, limits, threshold)
            prediction = lifter.lift(inputs.keypoints_2d, inputs.visible)
        except LiftError as err:
            raise LiftClientError(str(err), "rejected") from err
        replies = to_pose_results(inputs, prediction)  # the same fields as the HTTP reply
        return [LiftResult.from_fields(d.__getitem__, joints, model_id) for d in replies]

    return lift


def result_json(result: LiftResult, points: np.ndarray, conf: np.ndarray | None) -> dict[str, Any]:
    """One pose of the output file: its input and every field of the service's reply."""
    keypoints = [None if np.isnan(p).any() else p.tolist() for p in points]
    return {"input": {"keypoints": keypoints, "confidence": None if conf is None else conf.tolist()},
            "pose_3d": result.pose_3d.tolist(), "pose_3d_camera": result.pose_3d_camera.tolist(),
            "camera": result.camera.tolist(), "scale": result.scale, "rotation": result.rotation.tolist(),
            "reprojection": result.reprojection.tolist(),
            "reprojection_error_px": result.reprojection_error_px,
            "visible": result.visible.tolist(), "imputed": result.imputed.tolist(),
            "derived": result.derived.tolist(), "plausibility": result.plausibility}  # fmt: skip


def run_lift(args: argparse.Namespace) -> int:
    poses = load_poses(args.input)
    fmt = args.format or poses.format or "h36m17"
    if fmt not in FORMATS:
        raise InputFileError(f"unknown format {fmt!r}; expected one of {', '.join(FORMATS)}")
    if poses.points.shape[1] != len(FORMATS[fmt].joint_names):
        raise InputFileError(f"{args.input}: poses have {poses.points.shape[1]} joints, format {fmt} has "
                             f"{len(FORMATS[fmt].joint_names)}; pick the format with --format")  # fmt: skip
    if args.local:
        lift, close = _local_lift(args.model, fmt, args.confidence_threshold, args.batch_size), None
    else:
        lift, close = _remote_lift(args.url, fmt, args.confidence_threshold, args.timeout)
    n, size = len(poses.points), args.batch_size
    starts = list(range(0, n, size))
    results: list[LiftResult] = []
    try:
        for a in _progress(starts, len(starts), enabled=n > size):
            conf = None if poses.confidence is None else poses.confidence[a : a + size]
            try:
                results.extend(lift(poses.points[a : a + size], conf))
            except LiftClientError as err:
                raise LiftClientError(_shift_pose_indices(err.message, a), err.status, err.details) from err
    finally:
        if close is not None:
            close.close()
    conf = poses.confidence
    out = {"model_id": results[0].model_id, "format": fmt, "input_joints": list(FORMATS[fmt].joint_names),
           "joints": list(results[0].joints), "parents": list(MODEL_PARENTS),
           "poses": [result_json(r, poses.points[i], None if conf is None else conf[i])
                     for i, r in enumerate(results)]}  # fmt: skip
    text = json.dumps(out, allow_nan=False)
    if args.output is None:
        print(text)
    else:
        args.output.write_text(text)
        print(f"lifted {n} poses ({fmt}, model {out['model_id']}) -> {args.output}", file=sys.stderr)
    return EXIT_OK


def run_plot(args: argparse.Namespace) -> int:
    from service.plot import plot_lift_file

    try:
        plot_lift_file(args.input, args.output, args.index)
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise InputFileError(str(err)) from err
    print(f"wrote {args.output}", file=sys.stderr)
    return EXIT_OK


def run_formats(args: argparse.Namespace) -> int:
    print(format_table())
    return EXIT_OK


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="repnet", description="RepNet 2D-to-3D pose lifting.")
    sub = parser.add_subparsers(dest="command", required=True)
    serve = sub.add_parser("serve", help="run the HTTP and gRPC server (python -m service; see --help)",
                           add_help=False)  # fmt: skip
    serve.add_argument("args", nargs=argparse.REMAINDER)
    lift = sub.add_parser("lift", help="lift the poses of a .json or .npz file to 3D")
    lift.add_argument("input", type=Path, help=".json or .npz file of one or many poses")
    lift.add_argument("--format", choices=list(FORMATS), help="keypoint format (default: file's, h36m17)")
    lift.add_argument("--url", default=DEFAULT_URL, help=f"service URL (default {DEFAULT_URL})")
    lift.add_argument("--local", action="store_true", help="run the ONNX model in this process, no service")
    lift.add_argument("--model", type=Path, help="ONNX model for --local (default: the bundled one)")
    lift.add_argument("--confidence-threshold", type=float, help="joints below it count as missing")
    lift.add_argument("--batch-size", type=int, default=256, help="poses per request (default 256)")
    lift.add_argument("--timeout", type=float, default=30.0, help="seconds per request (default 30)")
    lift.add_argument("-o", "--output", type=Path, help="output .json (default: stdout)")
    plot = sub.add_parser("plot", help="draw a lift output: 2D input with reprojection, 3D from two sides")
    plot.add_argument("input", type=Path, help="output .json of `repnet lift`")
    plot.add_argument("-o", "--output", type=Path, required=True, help="image file (.png, .svg, .pdf)")
    plot.add_argument("--index", type=int, default=0, help="which pose of the file (default 0)")
    sub.add_parser("formats", help="print how each keypoint format maps onto the model's 17 joints")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["serve"]:  # every flag, --help included, belongs to the server's own parser
        from service.__main__ import main as serve

        return serve(argv[1:])
    args = build_parser().parse_args(argv)
    if args.command == "lift" and args.model is not None and not args.local:
        print("repnet: error: --model needs --local", file=sys.stderr)
        return EXIT_USAGE
    if args.command == "lift" and args.batch_size < 1:
        print("repnet: error: --batch-size must be at least 1", file=sys.stderr)
        return EXIT_USAGE
    commands = {"lift": run_lift, "plot": run_plot, "formats": run_formats}
    try:
        return commands[args.command](args)
    except (InputFileError, ModelLoadError) as err:
        print(f"repnet: error: {err}", file=sys.stderr)
        return EXIT_USAGE
    except LiftClientError as err:
        hint = " (start it with `repnet serve`, or lift with --local)" if err.status is None else ""
        print(f"repnet: error: {err}{hint}", file=sys.stderr)
        return EXIT_UNREACHABLE if err.status is None else EXIT_REJECTED
    except BrokenPipeError:  # `repnet formats | head`: the reader left; say nothing more
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return EXIT_OK
    except ImportError as err:
        print(f"repnet: error: {err.name or err} is needed: pip install 'repnet[cli]'", file=sys.stderr)
        return EXIT_USAGE


if __name__ == "__main__":
    sys.exit(main())
