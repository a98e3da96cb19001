"""The values of the repnet command's flags, checked as argparse reads them: intrinsics, a format, a
positive number, an image side, a frame rate."""

from __future__ import annotations

import argparse
import math

from repnet.cli.adapt import format_error
from repnet.client.body import Intrinsics
from repnet.core.contract import MAX_FPS
from repnet.core.formats import FORMATS


def intrinsics_flag(text: str) -> Intrinsics:
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


def format_flag(text: str) -> str:
    """--format: a format's name."""
    if text not in FORMATS:
        raise argparse.ArgumentTypeError(format_error(text))
    return text


def number_flag(text: str) -> float:
    """A flag's number; NaN (which every range check refuses) when it is not one."""
    try:
        return float(text)
    except ValueError:
        return math.nan


def size_flag(text: str) -> float:
    """One value of --image-size: a number of pixels > 0."""
    value = number_flag(text)
    if not 0 < value < math.inf:
        raise argparse.ArgumentTypeError(f"expected a number of pixels > 0, got {text!r}")
    return value


def fps_flag(text: str) -> float:
    """--fps: a number in (0, 240]."""
    value = number_flag(text)
    if not 0 < value <= MAX_FPS:
        raise argparse.ArgumentTypeError(f"expected frames per second in (0, {MAX_FPS:g}], got {text!r}")
    return value
