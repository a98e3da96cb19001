"""The command line the Human3.6M accuracy benchmarks share: the model, the data folder, the
onnxruntime threads, and the frame step's check."""

from __future__ import annotations

import argparse
from pathlib import Path

from repnet.runtime.loading import BUNDLED_MODEL
from repnet.train import data


def h36m_parser(module: str, doc: str | None) -> argparse.ArgumentParser:
    """`python -m bench.<module>`'s parser with --model, --data-dir and --threads."""
    parser = argparse.ArgumentParser(
        prog=f"python -m bench.{module}",
        description=doc,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "--model", type=Path, default=BUNDLED_MODEL, help="ONNX model (default: the bundled one)"
    )
    parser.add_argument("--data-dir", default=None, help=f"Human3.6M folder (default: ${data.DATA_ENV})")
    parser.add_argument("--threads", type=int, default=0, help="onnxruntime threads (0: one per core)")
    return parser


def check_frame_step(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Exit with a usage error unless --frame-step is at least 1."""
    if args.frame_step < 1:
        parser.error(f"--frame-step must be >= 1, got {args.frame_step}")
