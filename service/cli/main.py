"""The `repnet` command: serve, lift files of poses (via the service or locally), lift the people of a
video, plot, list formats."""

from __future__ import annotations

import argparse
import importlib
import json
import os
import sys
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any, TextIO, TypeVar

from repnet.cli import adapt, video
from repnet.cli.adapt import add_parser as add_adapt_parser
from repnet.cli.adapt import resolve_format
from repnet.cli.flags import format_flag, size_flag
from repnet.cli.lift import lift_poses, say, tell_written
from repnet.cli.options import add_lift_options
from repnet.client.http import LiftClientError
from repnet.core.errors import ModelLoadError
from repnet.core.format_hints import format_table
from repnet.core.formats import FORMATS
from repnet.io.output import WRITERS, check_output, write_output
from repnet.io.pose_file import load_poses, read_input
from repnet.io.poses import InputFileError, Poses

__all__ = ["InputFileError", "Poses", "build_parser", "load_poses", "main"]

# Exit codes: 0 done; 1 the service or model rejected the input; 2 bad usage, input file or model
# file; 3 the service could not be reached.
EXIT_OK, EXIT_REJECTED, EXIT_USAGE, EXIT_UNREACHABLE = 0, 1, 2, 3
T = TypeVar("T")


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


def run_lift(args: argparse.Namespace) -> int:
    if args.output is not None:
        check_output(args.output, args.overwrite)
    size = None if args.image_size is None else (args.image_size[0], args.image_size[1])
    poses = read_input(args.input, lambda files: _progress(files, "file"), size)
    fmt = resolve_format(poses, args.format, args.input, say)
    lifted, choice = lift_poses(args, poses, fmt, args.temporal, progress_bar)
    if args.output is None:
        print(json.dumps(lifted.document, allow_nan=False))
    else:
        tell_written(write_output(args.output, lifted), lifted, choice)
    return EXIT_OK


def run_plot(args: argparse.Namespace) -> int:
    from repnet.io.plot import plot_lift_file

    bar = progress_bar(0, "frame")

    def advance(done: int, total: int) -> None:
        if bar is not None:
            bar.total = total
            bar.update(1)

    try:
        drawn = plot_lift_file(
            args.input, args.output, args.index, args.person, args.fps, advance, args.track
        )
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise InputFileError(str(err)) from err
    except RecursionError:
        raise InputFileError(f"{args.input}: the JSON is nested too deeply to read") from None
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
    serve = sub.add_parser(
        "serve", help="run the HTTP and gRPC server (python -m repnet serve; see --help)", add_help=False
    )
    serve.add_argument("args", nargs=argparse.REMAINDER)
    lift = sub.add_parser("lift", help="lift the poses of a detector's file (.json, .npz, .txt) to 3D")
    lift.add_argument(
        "input",
        help="a detector's .json, .npz or .txt file (README: the files read), or a folder or glob of "
        "per-frame files (OpenPose --write_json, YOLO save_txt labels), taken by frame number",
    )
    lift.add_argument(
        "--format",
        type=format_flag,
        metavar="{" + ",".join(FORMATS) + "}",
        help="keypoint format (default: file's, h36m17)",
    )
    lift.add_argument(
        "--image-size",
        type=size_flag,
        nargs=2,
        metavar=("W", "H"),
        help="the image's width and height in px when x, y are normalised to [0, 1] "
        "(MediaPipe landmarks, YOLO label files): they are multiplied by it",
    )
    add_lift_options(
        lift,
        "offline for a folder or a file of several frames, off for one frame",
        "the file's, else 30, said on stderr",
    )
    lift.add_argument(
        "-o",
        "--output",
        type=Path,
        help=f"output file by its suffix ({', '.join(WRITERS)}; default: JSON on stdout): .npz "
        "arrays named as the reply's fields, .csv a row per pose per joint, .bvh a skeleton "
        "animation per person (file.track-ID.bvh when several)",
    )
    plot = sub.add_parser("plot", help="draw a lift output: 2D input with reprojection, 3D from two sides")
    plot.add_argument("input", type=Path, help="output .json of `repnet lift`")
    plot.add_argument(
        "-o",
        "--output",
        type=Path,
        required=True,
        help="image file (.png, .svg, .pdf), or an animation of the sequence (.gif; .mp4 "
        "where ffmpeg is installed)",
    )
    plot.add_argument("--index", type=int, default=0, help="which pose of the file, for an image (default 0)")
    plot.add_argument("--person", type=int, default=0, help="whose poses to animate (default 0)")
    plot.add_argument("--track", help="animate this track's poses (the output's track_id) instead")
    plot.add_argument("--fps", type=int, default=10, help="frames per second of an animation (default 10)")
    sub.add_parser("formats", help="print how each keypoint format maps onto the model's 17 joints")
    video.add_parser(sub)
    add_adapt_parser(sub, size_flag, format_flag)
    return parser


def usage_error(args: argparse.Namespace) -> str | None:
    """What is wrong with the command's flags beyond what argparse checks, if anything."""
    if args.command == "lift" and args.batch_size < 1:
        return "--batch-size must be at least 1"
    if args.command == "plot" and args.fps < 1:
        return "--fps must be at least 1"
    return video.check_args(args) if args.command == "video" else None


def main(argv: Sequence[str] | None = None) -> int:
    """Run the `repnet` command; the exit status (EXIT_*)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["serve"]:  # every flag, --help included, belongs to the server's own parser
        try:
            from repnet.server.app import main as serve
        except ImportError as err:
            print(f"repnet: error: serve needs {err.name or err}: {install_hint('server')}", file=sys.stderr)
            return EXIT_USAGE
        return serve(argv[1:])
    args = build_parser().parse_args(argv)
    if args.command == "adapt":  # its lineage records the command
        args.command_line = ["repnet", *argv]
    if wrong := usage_error(args):
        print(f"repnet: error: {wrong}", file=sys.stderr)
        return EXIT_USAGE
    commands = {
        "lift": run_lift,
        "plot": run_plot,
        "formats": run_formats,
        "adapt": run_adapt,
        "video": run_video,
    }
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
        # `repnet video` needs its whole extra (PyAV, OpenCV, Pillow and onnxruntime for its detector)
        extra = "video" if args.command == "video" else EXTRAS.get((err.name or "").split(".")[0], "cli")
        print(f"repnet: error: {err.name or err} is needed: {install_hint(extra)}", file=sys.stderr)
        return EXIT_USAGE


def run_video(args: argparse.Namespace) -> int:
    """`repnet video`: repnet.cli.video, with the command's progress bars."""
    return video.run(args, progress_bar)


def run_adapt(args: argparse.Namespace) -> int:
    """`repnet adapt`: repnet.train.adapt_cli, which needs the `train` extra (torch)."""
    return adapt.run(args)


# The extra (pyproject.toml) that brings a module a command needs.
EXTRAS = {
    "onnxruntime": "local",
    **dict.fromkeys(
        [
            "fastapi",
            "starlette",
            "uvicorn",
            "pydantic",
            "pydantic_settings",
            "prometheus_client",
            "grpc_health",
            "grpc_reflection",
            "fastapi_offline",
        ],
        "server",
    ),
    **dict.fromkeys(["matplotlib", "tqdm"], "cli"),
    **dict.fromkeys(["av", "PIL", "cv2"], "video"),
    **dict.fromkeys(["torch", "sklearn", "onnx"], "train"),
}


def install_hint(extra: str = "cli") -> str:
    """How to install an extra of repnet into this interpreter: from the checkout this package runs
    from (`make serve` installs server and cli, `make test` all), else from the package index."""
    root = Path(__file__).resolve().parents[2]
    pip = f"{sys.executable} -m pip install"
    if (root / "pyproject.toml").is_file():
        return f"{pip} -e '{root}[{extra}]' (the checkout's `make serve` and `make test` install it too)"
    return f"{pip} 'repnet[{extra}]' (the `{extra}` extra of repnet)"


if __name__ == "__main__":
    sys.exit(main())
