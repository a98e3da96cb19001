"""The `repnet` command: serve, lift files of poses (via the service or locally), plot, list formats."""

from __future__ import annotations

import argparse
import importlib
import json
import math
import os
import re
import sys
from collections.abc import Callable, Iterable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any, TextIO, TypeVar

import numpy as np

from service.client import DEFAULT_URL, LiftClient, LiftClientError, LiftResult
from service.errors import ModelLoadError
from service.formats import FORMATS, MODEL_PARENTS, format_table
from service.pose_file import InputFileError, Poses, load_poses, read_input

__all__ = ["InputFileError", "Poses", "build_parser", "load_poses", "main"]

# Exit codes: 0 done; 1 the service or model rejected the input; 2 bad usage, input file or model
# file; 3 the service could not be reached.
EXIT_OK, EXIT_REJECTED, EXIT_USAGE, EXIT_UNREACHABLE = 0, 1, 2, 3
T = TypeVar("T")
Lift = Callable[[np.ndarray, "np.ndarray | None"], list[LiftResult]]


def _shift_pose_indices(message: str, offset: int) -> str:
    """Rename poses[i] to poses[offset + i] in a message about one chunk of the file."""
    return re.sub(r"poses\[(\d+)\]", lambda m: f"poses[{offset + int(m.group(1))}]", message)


def progress_bar(total: int, unit: str, file: TextIO | None = None) -> Any:
    """A tqdm bar on stderr, shown only when it is a terminal and the work lasts over half a second;
    None without tqdm (progress bars are optional: pip install 'repnet[cli]')."""
    try:
        tqdm = importlib.import_module("tqdm").tqdm
    except ImportError:
        return None
    return tqdm(total=total, unit=unit, file=file or sys.stderr, disable=None, delay=0.5, leave=False)


def _progress(items: Sequence[T], unit: str) -> Iterable[T]:
    """`items`, advancing a progress bar (see progress_bar) as they are taken."""
    bar = progress_bar(len(items), unit)
    if bar is None:
        return items

    def advance() -> Iterable[T]:
        with bar:
            for item in items:
                yield item
                bar.update(1)

    return advance()


Intrinsics = tuple[float, float, float, float]


def _remote_lift(args: argparse.Namespace, fmt: str) -> tuple[Lift, LiftClient]:
    client = LiftClient(args.url, timeout=args.timeout, api_key=args.api_key, ca_file=args.ca_file)
    threshold, intrinsics = args.confidence_threshold, args.intrinsics

    def lift(points: np.ndarray, conf: np.ndarray | None) -> list[LiftResult]:
        return client.lift_batch(
            points, format=fmt, confidence=conf, confidence_threshold=threshold, intrinsics=intrinsics
        )

    return lift, client


def _local_lift(
    model: Path | None, fmt: str, threshold: float | None, batch: int, intrinsics: Intrinsics | None
) -> Lift:
    """Lift in this process with the core the servers use: load checks, input rules, the reply."""
    from service.app import limits_of, load_lifter
    from service.config import Settings
    from service.errors import LiftError
    from service.keypoints import PoseInput, prepare_request
    from service.replies import build_replies

    settings = Settings() if model is None else Settings(model_path=model)
    lifter = load_lifter(settings)
    limits = replace(limits_of(settings), max_request_poses=batch)  # --batch-size poses per request
    joints, model_id = lifter.info.joint_names, lifter.info.model_id

    def lift(points: np.ndarray, conf: np.ndarray | None) -> list[LiftResult]:
        poses = [PoseInput(p, ~np.isnan(p).any(axis=1), None if conf is None else conf[i], fmt, intrinsics)
                 for i, p in enumerate(points)]  # fmt: skip
        try:
            inputs = prepare_request(len(poses), poses.__getitem__, threshold, limits)
            replies = build_replies(inputs, lifter.lift(inputs.keypoints_2d, inputs.visible)).check()
        except LiftError as err:
            raise LiftClientError(str(err), "rejected") from err
        return [LiftResult.from_fields(d.__getitem__, joints, model_id) for d in replies.to_json()]

    return lift


def _intrinsics(text: str) -> Intrinsics:
    """--intrinsics FX,FY,CX,CY: four finite numbers, the focal lengths > 0."""
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 4 or not all(math.isfinite(v) for v in values) or min(values[:2]) <= 0:
        raise argparse.ArgumentTypeError(
            f"expected FX,FY,CX,CY (4 finite numbers, FX and FY > 0), got {text!r}"
        )
    return (values[0], values[1], values[2], values[3])


def result_json(result: LiftResult, points: np.ndarray, conf: np.ndarray | None) -> dict[str, Any]:
    """One pose of the output file: its input and every field of the service's reply. A missing
    joint is null in both `keypoints` and `confidence`."""
    missing = np.isnan(points).any(axis=1)  # (J,)
    keypoints = [None if gone else p.tolist() for p, gone in zip(points, missing, strict=True)]
    confidence = None if conf is None else [None if gone else float(c)
                                            for c, gone in zip(conf, missing, strict=True)]  # fmt: skip
    fields = {name: _json_value(getattr(result, name)) for name in LiftResult.pose_fields()}
    return {"input": {"keypoints": keypoints, "confidence": confidence}, **fields}


def _json_value(value: Any) -> Any:
    """A LiftResult field as JSON: arrays as nested lists, tuples as lists."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    return list(value) if isinstance(value, tuple) else value


def warn_about(results: Sequence[LiftResult], poses: Poses) -> None:
    """Say on stderr how many poses got a warning, with the first of each kind and where it was."""
    kinds: dict[str, list[int]] = {}
    for i, result in enumerate(results):
        for warning in result.warnings:
            kinds.setdefault(warning.split(" (")[0], []).append(i)
    for kind, where in kinds.items():
        first = where[0]
        message = next(w for w in results[first].warnings if w.startswith(kind))
        print(f"repnet: warning: {len(where)} of {len(results)} poses: {message} (first: poses[{first}], "
              f"frame {poses.frame[first]}, person {poses.person[first]})", file=sys.stderr)  # fmt: skip


def _lift_all(lift: Lift, poses: Poses, size: int) -> list[LiftResult]:
    """Lift `poses` in requests of `size`, with a progress bar for long inputs."""
    n = len(poses.points)
    results: list[LiftResult] = []
    bar = progress_bar(n, "pose")
    try:
        for a in range(0, n, size):
            conf = None if poses.confidence is None else poses.confidence[a : a + size]
            try:
                results.extend(lift(poses.points[a : a + size], conf))
            except LiftClientError as err:
                raise LiftClientError(_shift_pose_indices(err.message, a), err.status, err.details) from err
            if bar is not None:
                bar.update(min(size, n - a))
    finally:
        if bar is not None:
            bar.close()
    return results


def run_lift(args: argparse.Namespace) -> int:
    poses = read_input(args.input, lambda files: _progress(files, "file"))
    fmt = args.format or poses.format or "h36m17"
    if fmt not in FORMATS:
        raise InputFileError(f"unknown format {fmt!r}; expected one of {', '.join(FORMATS)}")
    if poses.points.shape[1] != len(FORMATS[fmt].joint_names):
        raise InputFileError(f"{args.input}: poses have {poses.points.shape[1]} joints, format {fmt} has "
                             f"{len(FORMATS[fmt].joint_names)}; pick the format with --format")  # fmt: skip
    if args.local:
        lift = _local_lift(args.model, fmt, args.confidence_threshold, args.batch_size, args.intrinsics)
        close = None
    else:
        lift, close = _remote_lift(args, fmt)
    try:
        results = _lift_all(lift, poses, args.batch_size)
    finally:
        if close is not None:
            close.close()
    conf = poses.confidence
    out = {"model_id": results[0].model_id, "format": fmt, "input_joints": list(FORMATS[fmt].joint_names),
           "joints": list(results[0].joints), "parents": list(MODEL_PARENTS),
           "poses": [{"frame": int(poses.frame[i]), "person": int(poses.person[i]),
                      **result_json(r, poses.points[i], None if conf is None else conf[i])}
                     for i, r in enumerate(results)]}  # fmt: skip
    warn_about(results, poses)
    text = json.dumps(out, allow_nan=False)
    n, frames = len(results), len(set(poses.frame.tolist()))
    if args.output is None:
        print(text)
    else:
        args.output.write_text(text)
        print(f"lifted {n} poses of {frames} frames ({fmt}, model {out['model_id']}) -> {args.output}",
              file=sys.stderr)  # fmt: skip
    return EXIT_OK


def run_plot(args: argparse.Namespace) -> int:
    from service.plot import plot_lift_file

    bar = progress_bar(0, "frame")

    def advance(done: int, total: int) -> None:
        if bar is not None:
            bar.total = total
            bar.update(1)

    try:
        drawn = plot_lift_file(args.input, args.output, args.index, args.person, args.fps, advance)
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise InputFileError(str(err)) from err
    finally:
        if bar is not None:
            bar.close()
    print(f"wrote {args.output} ({drawn} {'pose' if drawn == 1 else 'frames'})", file=sys.stderr)
    return EXIT_OK


def run_formats(args: argparse.Namespace) -> int:
    print(format_table())
    return EXIT_OK


def build_parser() -> argparse.ArgumentParser:
    """The `repnet` argument parser with its subcommands."""
    parser = argparse.ArgumentParser(prog="repnet", description="RepNet 2D-to-3D pose lifting.")
    sub = parser.add_subparsers(dest="command", required=True)
    serve = sub.add_parser("serve", help="run the HTTP and gRPC server (python -m service; see --help)",
                           add_help=False)  # fmt: skip
    serve.add_argument("args", nargs=argparse.REMAINDER)
    lift = sub.add_parser("lift", help="lift the poses of a .json or .npz file to 3D")
    lift.add_argument("input", help=".json or .npz file of one or many poses, or a folder or glob "
                      "of per-frame .json files (OpenPose --write_json), taken by frame number")  # fmt: skip
    lift.add_argument("--format", choices=list(FORMATS), help="keypoint format (default: file's, h36m17)")
    lift.add_argument("--url", default=DEFAULT_URL, help=f"service URL (default {DEFAULT_URL})")
    lift.add_argument("--local", action="store_true", help="run the ONNX model in this process, no service")
    lift.add_argument("--model", type=Path, help="ONNX model for --local (default: the bundled one)")
    lift.add_argument("--confidence-threshold", type=float, help="joints below it count as missing")
    lift.add_argument(
        "--intrinsics",
        type=_intrinsics,
        metavar="FX,FY,CX,CY",
        help="the camera's focal lengths and principal point in px, if known: pose_3d_camera "
        "is then turned along the ray to the person",
    )
    lift.add_argument("--batch-size", type=int, default=256, help="poses per request (default 256)")
    lift.add_argument("--timeout", type=float, default=30.0, help="seconds per request (default 30)")
    lift.add_argument("--api-key", default=os.environ.get("REPNET_API_KEY"),
                      help="API key of a service with REPNET_API_KEYS_FILE (default: $REPNET_API_KEY; "
                      "the variable keeps it out of the process list)")  # fmt: skip
    lift.add_argument(
        "--ca-file", type=Path, help="PEM CA certificates of an https:// --url (default: the system's)"
    )
    lift.add_argument("-o", "--output", type=Path, help="output .json (default: stdout)")
    plot = sub.add_parser("plot", help="draw a lift output: 2D input with reprojection, 3D from two sides")
    plot.add_argument("input", type=Path, help="output .json of `repnet lift`")
    plot.add_argument("-o", "--output", type=Path, required=True,
                      help="image file (.png, .svg, .pdf), or an animation of the sequence (.gif; .mp4 "
                      "where ffmpeg is installed)")  # fmt: skip
    plot.add_argument("--index", type=int, default=0, help="which pose of the file, for an image (default 0)")
    plot.add_argument("--person", type=int, default=0, help="whose poses to animate (default 0)")
    plot.add_argument("--fps", type=int, default=10, help="frames per second of an animation (default 10)")
    sub.add_parser("formats", help="print how each keypoint format maps onto the model's 17 joints")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the `repnet` command; the exit status (EXIT_*)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["serve"]:  # every flag, --help included, belongs to the server's own parser
        from service.app import main as serve

        return serve(argv[1:])
    args = build_parser().parse_args(argv)
    if args.command == "lift" and args.model is not None and not args.local:
        print("repnet: error: --model needs --local", file=sys.stderr)
        return EXIT_USAGE
    if args.command == "lift" and args.batch_size < 1:
        print("repnet: error: --batch-size must be at least 1", file=sys.stderr)
        return EXIT_USAGE
    if args.command == "plot" and args.fps < 1:
        print("repnet: error: --fps must be at least 1", file=sys.stderr)
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
