"""Format mix-ups: a pose under the wrong 17-joint label, told by its geometry, reprojection and plausibility.

coco17 keypoints sent as h36m17 (the default) or back give the reply's format warning."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from repnet.core.format_hints import lookalike_of
from repnet.core.formats import COCO17, FORMAT_NAMES, H36M17
from repnet.core.geometry import FloatArray, visible_spread
from repnet.core.inputs import ModelInput

# The mix-up score of a pose is its reprojection error as a fraction of its spread (the standard
# deviation of its visible coordinates) plus GEOMETRY_WEIGHT times the geometric evidence (in
# [-1, 1]) that it is in the other format; a warning is given above THRESHOLD. Chosen on
# Human3.6M S1-S8 and measured on S9/S11 by bench/format_mixup.py (docs/BENCHMARKS.md). With the
# bundled repnet-h36m-v6 on S1-S8 (every 10th frame), poses in the right format have a relative
# reprojection error under 0.198 (h36m17) and 0.227 (coco17) at the 99.5th percentile, the same
# poses under the wrong label over 0.75 at the 0.5th: the threshold sits between (v5: 0.205, 0.231
# and 0.72; v4: 0.200, 0.226 and 0.66; v3: 0.225, 0.255 and 0.68; v2: 0.25, 0.28 and 0.79). (v1,
# which fitted the 2D more tightly, had 0.21 and 0.30 and a threshold of 0.25.)
GEOMETRY_WEIGHT = 0.05
THRESHOLD = 0.5
# With a plausibility output (a percentile among real poses), a 3D pose below PLAUSIBILITY_FLOOR
# adds PLAUSIBILITY_WEIGHT to the score: a wrong reading of the joints rarely lifts to a real pose.
PLAUSIBILITY_FLOOR = 0.01
PLAUSIBILITY_WEIGHT = 0.05

# Why the geometry points to the other format, for each given format.
_GEOMETRY_NOTE = {
    H36M17.name: "joint 0 sits above the shoulders (5, 6) like COCO's nose, not between the hips",
    COCO17.name: "joint 0 is not above the shoulders (5, 6) as COCO's nose would be",
}


# Per format in FORMAT_NAMES: it has a lookalike, and the sign that turns nose_height into evidence
# for that lookalike (a nose above the shoulders says coco17; below, h36m17).
_HAS_LOOKALIKE = np.array([lookalike_of(name) is not None for name in FORMAT_NAMES])
_TOWARD_LOOKALIKE = np.array([{H36M17.name: 1.0, COCO17.name: -1.0}.get(name, 0.0) for name in FORMAT_NAMES])


def geometric_evidence(inputs: ModelInput) -> npt.NDArray[np.float64]:
    """(N,) the evidence in [-1, 1] from nose_height that each pose is in its format's lookalike
    (0 where it cannot be read)."""
    height = np.clip(np.nan_to_num(inputs.nose_height.astype(np.float64), nan=0.0), -1.0, 1.0)
    return np.asarray(height * _TOWARD_LOOKALIKE[inputs.format_index], np.float64)


def relative_error(
    inputs: ModelInput, error_px: FloatArray, spread: np.ndarray | None = None
) -> npt.NDArray[np.float64]:
    """(N,) reprojection error (N,) px as a fraction of the pose's spread (visible_spread of its
    input, when the caller has it): the same for any image size."""
    spread = visible_spread(inputs.keypoints_2d, inputs.visible) if spread is None else spread  # (N,) px
    return error_px.astype(np.float64) / np.maximum(spread, 1e-9)


def mixup_scores(
    inputs: ModelInput,
    error_px: FloatArray,
    plausibility: FloatArray | None,
    relative: npt.NDArray[np.float64] | None = None,
) -> npt.NDArray[np.float64]:
    """(N,) the mix-up score of each pose (NaN for a format without a lookalike) from its reprojection
    error (N,) px and the model's plausibility (N,) if it has one; `relative`: relative_error, when
    the caller has it."""
    relative = relative_error(inputs, error_px) if relative is None else relative
    scores = relative + GEOMETRY_WEIGHT * geometric_evidence(inputs)
    if plausibility is not None:
        scores = scores + PLAUSIBILITY_WEIGHT * (plausibility < PLAUSIBILITY_FLOOR)
    return np.where(_HAS_LOOKALIKE[inputs.format_index], scores, np.nan)


def format_warnings(
    inputs: ModelInput,
    error_px: FloatArray,
    plausibility: FloatArray | None,
    spread: np.ndarray | None = None,
) -> list[list[str]]:
    """Per pose, the warnings of its reply: today at most one, that the format looks wrong
    (`spread`: visible_spread of the inputs, when the caller has it)."""
    relative = relative_error(inputs, error_px, spread)
    out: list[list[str]] = [[] for _ in range(len(inputs))]
    flagged = np.flatnonzero(mixup_scores(inputs, error_px, plausibility, relative) > THRESHOLD)  # NaN: False
    if not len(flagged):
        return out
    evidence = geometric_evidence(inputs)
    for i in flagged:
        given = FORMAT_NAMES[inputs.format_index[i]]
        other = lookalike_of(given)
        geometry = "; " + _GEOMETRY_NOTE[given] if evidence[i] > 0 else ""
        out[i].append(
            f"format: these keypoints look like {other}, not {given} (reprojection error "
            f"{relative[i]:.0%} of the pose's size, rare above {THRESHOLD:.0%} in the right format"
            f'{geometry}); if they are {other}, send format "{other}"'
        )
    return out
