"""The flags `repnet lift` and `repnet video` share: where the poses are lifted (the service or this
process, which model), the input rules, the camera, the temporal mode and frame rate, the requests."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from repnet.cli.adapt import threshold_flag
from repnet.cli.flags import fps_flag, intrinsics_flag
from repnet.client.connection import DEFAULT_URL
from repnet.core.contract import TEMPORAL_MODES


def add_lift_options(parser: argparse.ArgumentParser, temporal_default: str, fps_default: str) -> None:
    """The shared flags on `parser`; the defaults of --temporal and --fps as its help says them."""
    parser.add_argument("--url", default=DEFAULT_URL, help=f"service URL (default {DEFAULT_URL})")
    parser.add_argument("--local", action="store_true", help="run the ONNX model in this process, no service")
    parser.add_argument(
        "--model",
        help="the model: a model_id the service serves (GET /v1/models; default: "
        "its default model), or with --local an ONNX file (default: the bundled one)",
    )
    parser.add_argument(
        "--confidence-threshold", type=threshold_flag, help="joints below it count as missing, in [0, 1]"
    )
    parser.add_argument(
        "--intrinsics",
        type=intrinsics_flag,
        metavar="FX,FY,CX,CY",
        help="the camera's focal lengths and principal point in px, if known: pose_3d_camera "
        "is then turned along the ray to the person, and root_camera_m gives where the person stands",
    )
    parser.add_argument(
        "--person-height",
        type=float,
        metavar="METRES",
        help="the person's skeleton height (head top to ankle, about stature - 0.1 m): sets "
        "root_camera_m's depth (default: the model's template size)",
    )
    parser.add_argument(
        "--temporal",
        choices=TEMPORAL_MODES,
        help="how a sequence's tracked people are lifted: off, each pose alone; causal, from "
        f"its track's frames up to it; offline, from the frames around it (default: {temporal_default})",
    )
    parser.add_argument(
        "--fps",
        type=fps_flag,
        help=f"frames per second of the sequence (default: {fps_default})",
    )
    parser.add_argument(
        "--batch-size",
        type=int,
        default=256,
        help="poses per request lifted alone (default 256); a temporal request holds "
        "as many as the service takes (max_temporal_poses)",
    )
    parser.add_argument("--timeout", type=float, default=30.0, help="seconds per request (default 30)")
    parser.add_argument(
        "--api-key",
        default=os.environ.get("REPNET_API_KEY"),
        help="API key of a service with REPNET_API_KEYS_FILE (default: $REPNET_API_KEY; "
        "the variable keeps it out of the process list)",
    )
    parser.add_argument(
        "--ca-file", type=Path, help="PEM CA certificates of an https:// --url (default: the system's)"
    )
    parser.add_argument(
        "--strict",
        action="store_true",
        help="refuse the input if a pose breaks the input rules (default: skip it, said in `skipped`)",
    )
    parser.add_argument(
        "--overwrite",
        action="store_true",
        help="replace an existing output file (default: refuse before lifting)",
    )
