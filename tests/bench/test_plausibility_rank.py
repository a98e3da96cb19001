"""bench.plausibility_rank: deciles, ratio and Spearman of a plausibility output, on a known lifter."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from bench import plausibility_rank
from repnet.runtime.replies import IMPLAUSIBLE_BELOW
from repnet.train import data
from tests.training.conftest import STANDING


def _lifter(error_mm: np.ndarray, plausibility: np.ndarray) -> Any:
    """A lifter that answers pose i with the truth, one joint off by error_mm[i], and that plausibility."""

    def lift(points: np.ndarray, visible: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        rows = points[:, 0, 0].astype(int)  # each input carries its row number
        pose = np.repeat(STANDING[None], len(rows), axis=0).astype(np.float32)
        pose[:, 13, 2] += error_mm[rows]
        return pose, np.zeros((len(rows), 2, 3), np.float32), plausibility[rows]

    return lift


def test_a_plausibility_that_falls_as_the_error_grows_ranks_perfectly_and_a_random_one_does_not() -> None:
    n = 500
    error = np.linspace(10.0, 400.0, n).astype(np.float32)
    points = np.zeros((n, 17, 2), np.float32)
    points[:, 0, 0] = np.arange(n)
    val = data.ValidationSet(
        np.repeat(STANDING[None], n, axis=0).astype(np.float32), points, np.ones((n, 17))
    )
    good = plausibility_rank.rank_shift(_lifter(error, 1.0 - error / 400.0), val, batch=64)
    assert good["spearman"] == pytest.approx(-1.0) and good["ratio"] > 5
    assert good["deciles_pa_mpjpe"] == sorted(good["deciles_pa_mpjpe"], reverse=True) and good["poses"] == n
    noise = np.random.default_rng(0).random(n).astype(np.float32)
    shuffled = plausibility_rank.rank_shift(_lifter(error, noise), val)
    assert abs(shuffled["spearman"]) < 0.15 and 0.6 < shuffled["ratio"] < 1.6
    assert "| gt |" in plausibility_rank.table({"m": {"gt": good}})
    # plausibility 1 - error / 400 over error 10..400: its 1st percentile, and the share the service warns
    plausibility = 1.0 - error / 400.0
    assert good["percentile_1"] == pytest.approx(np.percentile(plausibility, 1), abs=1e-6)
    warned = (plausibility < IMPLAUSIBLE_BELOW).mean()
    assert good["warned_share"] == pytest.approx(warned) and warned > 0
    with pytest.raises(ValueError, match="no plausibility output"):
        plausibility_rank.rank_shift(lambda p, v: (p, p, None), val)
