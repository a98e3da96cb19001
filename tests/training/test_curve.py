"""Validation curves: the table of one run and the side-by-side figure of several."""

from __future__ import annotations

import json
from pathlib import Path

from repnet.train import curve


def _history(path: Path, offset: float) -> Path:
    records = [{"step": 50, "minutes": 0.5, "rep": 1.0}]
    records += [
        {"step": s, "minutes": s / 100, "val_gt_pa_mpjpe": 90 - s / 10 + offset, "val_gt_symmetry": 50.0}
        for s in (200, 100)
    ]
    path.write_text("".join(json.dumps(r) + "\n" for r in records))
    return path


def test_table_has_one_row_per_validation_in_step_order(tmp_path: Path) -> None:
    records = curve.read_validations(_history(tmp_path / "h.jsonl", 0.0))
    assert [r["step"] for r in records] == [100, 200]
    table = curve.markdown_table(records).splitlines()
    assert table[0] == "| step | minutes | gt_pa_mpjpe | gt_symmetry |"
    assert table[2] == "| 100 | 1.0 | 80.0 | 50.0 |"


def test_several_runs_are_drawn_side_by_side(tmp_path: Path, capsys) -> None:
    a, b = _history(tmp_path / "a.jsonl", 0.0), _history(tmp_path / "b.jsonl", 5.0)
    png = tmp_path / "curves.png"
    curve.main(["--history", f"arm a={a}", f"arm b={b}", "--png", str(png)])
    out = capsys.readouterr().out
    assert "arm a:" in out and "arm b:" in out and "| 100 | 1.0 | 85.0 | 50.0 |" in out
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_equal_time_table_takes_each_runs_last_validation_within_the_time(tmp_path: Path) -> None:
    runs = {
        "a": curve.read_validations(_history(tmp_path / "a.jsonl", 0.0)),
        "late": [{"step": 10, "minutes": 9.0, "val_gt_pa_mpjpe": 1.0}],
    }
    rows = curve.equal_time_table(runs, 1.5).splitlines()
    assert rows[2].startswith("| a | 100 | 1.0 | 80.0 | – | – | 50.0 |")
    assert rows[3].startswith("| late | – | – |")


def test_many_runs_plot_one_panel_per_named_figure(tmp_path: Path) -> None:
    import matplotlib.image

    runs = {
        f"arm{i}": [{"step": s, "minutes": s / 10, "val_gt_pa_mpjpe": 60.0 - s - i, "val_gt_symmetry": 20.0}
                    for s in (1, 2, 3)]
        for i in range(12)
    }  # fmt: skip
    curve.plot_runs(runs, tmp_path / "arms.png", ("gt_pa_mpjpe", "gt_symmetry"))
    wide = matplotlib.image.imread(tmp_path / "arms.png")
    curve.plot_runs(runs, tmp_path / "one.png", ("gt_pa_mpjpe",))
    narrow = matplotlib.image.imread(tmp_path / "one.png")
    assert wide.shape[0] == narrow.shape[0] and wide.shape[1] == 2 * narrow.shape[1]


def test_a_temporal_runs_history_is_read_and_drawn_by_its_set_figures(tmp_path: Path) -> None:
    """repnet.train.temporal_train writes sh25_/sh50_/gt25_ figures without the val_ prefix."""
    path = tmp_path / "temporal.jsonl"
    rows = [{"step": 10, "minutes": 0.1, "position": 70.0}]
    rows += [
        {"step": s, "minutes": s / 100, "sh50_accel": 3.0 - s / 1000, "gt25_pa_mpjpe": 33.0}
        for s in (500, 1000)
    ]
    path.write_text("".join(json.dumps(r) + "\n" for r in rows))
    records = curve.read_validations(path)
    assert [r["step"] for r in records] == [500, 1000]
    assert curve.markdown_table(records).splitlines()[2] == "| 500 | 5.0 | 33.0 | 2.5 |"
    assert curve.figure(records[1], "sh50_accel") == 2.0 and curve.figure(
        records[1], "gt_pa_mpjpe"
    ) != curve.figure(records[1], "gt_pa_mpjpe")
    curve.plot_runs({"causal": records}, tmp_path / "t.png", ("sh50_accel", "gt25_pa_mpjpe"))
    assert (tmp_path / "t.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
