"""bench.compare_models: every model measured once per round, in turn, and tabled per round."""

from __future__ import annotations

from pathlib import Path

from bench import compare_models
from repnet.runtime.loading import BUNDLED_MODEL
from tests.conftest import load_model


def test_every_round_measures_every_model_and_the_table_shows_each_round(tmp_path: Path) -> None:
    copy = tmp_path / "copy.onnx"
    copy.write_bytes(BUNDLED_MODEL.read_bytes())
    results = compare_models.compare([BUNDLED_MODEL, copy], (1, 4), rounds=2, duration=0.01, threads=1)
    assert list(results) == [str(BUNDLED_MODEL), str(copy)]
    for rounds in results.values():
        assert len(rounds) == 2
        assert [(r.what, r.batch) for r in rounds[0]] == [
            ("session.run", 1),
            ("Lifter.lift", 1),
            ("session.run", 4),
            ("Lifter.lift", 4),
        ]
        assert all(r.calls >= 5 and r.seconds > 0 for rows in rounds for r in rows)
    text = compare_models.table(results)
    lines = text.splitlines()
    assert lines[0].startswith("| model | session.run batch 1 | Lifter.lift batch 1 | session.run batch 4")
    model_id = load_model(BUNDLED_MODEL).info.model_id
    assert (
        len(lines) == 4 and lines[2].startswith(f"| {model_id} |") and lines[3].startswith(f"| {model_id} |")
    )
    assert lines[2].count(" ms / ") == 2 and lines[2].count(" poses/s / ") == 2
