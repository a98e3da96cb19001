"""bench.temporal_load: the camera search, the roof per tracked pose, the report, and a tiny run
against a started server (its plumbing, not its timings)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from bench.roof import RoofRow
from bench.stats import Result
from bench.temporal_load import PEOPLE_KINDS, held, main, search
from bench.temporal_report import Report
from bench.temporal_roof import clip_windows, per_pose_roof
from repnet.runtime.lifter import Lifter
from repnet.runtime.temporal import Contract


def test_the_search_stops_at_the_first_count_not_held_then_halves_the_gap() -> None:
    limit = 41
    best, tried = search([8, 16, 32, 48, 64], lambda n: n <= limit, refine=4)
    assert best == 40 and tried == [8, 16, 32, 48, 40, 44]  # 40 held, 44 not: within 4
    assert search([8, 16], lambda n: True, refine=4) == (16, [8, 16])
    assert search([8, 16], lambda n: False, refine=4) == (0, [8, 4])
    assert search([16, 8], lambda n: n < 16, refine=0) == (8, [8, 16])


def result(
    name: str, frames: int, p99: float = 10.0, errors: int = 0, cameras: int = 1, **extra: object
) -> Result:
    latency = {"p50": p99 / 2, "p99": p99}
    return Result(name, cameras, frames, frames, 1.0, latency, errors, 0.5, 0.1, dict(extra))


def test_cameras_are_held_with_p99_in_bounds_no_errors_and_every_frame_answered() -> None:
    assert held(result("c", 300, offered=300.0, sent=300), 25)
    assert not held(result("c", 300, p99=26, offered=300.0, sent=300), 25)
    assert not held(result("c", 300, errors=1, offered=300.0, sent=300), 25)
    assert not held(result("c", 280, offered=300.0, sent=300), 25)  # the server fell behind
    assert not held(result("c", 300, offered=300.0, sent=280), 25)  # the client fell behind


def test_a_short_window_holds_cameras_one_frame_short_each_at_its_edges_but_not_more() -> None:
    # 2 cameras at 30 fps for 0.6 s: 36 frames offered; 98 % alone would ask for all 36
    assert held(result("c", 34, cameras=2, offered=36.0, sent=35), 25)
    assert not held(result("c", 33, cameras=2, offered=36.0, sent=36), 25)  # the server fell behind
    assert not held(result("c", 36, cameras=2, offered=36.0, sent=33), 25)  # the client fell behind


def test_the_roof_per_tracked_pose_costs_one_run_of_each_model() -> None:
    rows = [RoofRow("session.run", 8, 100, 1.0, {}), RoofRow("temporal session.run", 8, 300, 1.0, {})]
    assert per_pose_roof(rows) == {8: {"single": 800.0, "temporal": 2400.0, "both": 600.0}}


def report(people: list[Result], **more: object) -> Report:
    roof = [RoofRow("session.run", 1, 100, 1.0, {}), RoofRow("temporal session.run", 1, 100, 1.0, {})]
    return Report(
        when="", command="python -m bench.temporal_load", machine={"cpus": 2, "cpu": "x"}, models={},
        contract={}, service_flags=[], roof=roof, most_cameras=24, searched=[8, 16, 32, 24, 28],
        people=people, **more,  # type: ignore[arg-type]
    )  # fmt: skip


def camera(count: int, frames: int, server_cpu: float, tracked: bool) -> Result:
    return Result(f"{count} cameras", count, frames, frames, 1.0, {"p50": 3.0, "p99": 9.0}, 0, server_cpu,
                  0.1, {"tracked": tracked, "held": True})  # fmt: skip


def test_the_report_gives_each_target_of_the_fast_path_met_or_missed_with_its_figure() -> None:
    one = result(PEOPLE_KINDS["pose"], 100, people=1, server_cpu_ms_per_frame=2.0)
    many = result("16 people (people)", 50, p99=30.0, people=16, server_cpu_ms_per_frame=5.0)
    cameras = [camera(8, 240, 0.72, True), camera(8, 240, 0.12, False), camera(16, 480, 1.0, True)]
    saturated = [result("x8, tracked", 45, tracked=True), result("x8, untracked", 90, tracked=False)]
    one_worker = [result("x8, tracked, --workers 1", 30, tracked=True)]
    floor = [camera(8, 240, 0.04, True), result("(echo floor) 1 streams, 256 in flight", 100)]
    floor[0].name = "(echo floor) 8 cameras at 30 fps"
    r = report([one, many], cameras=cameras, saturated=saturated, one_worker=one_worker, floor=floor)
    assert r.people_ratio() == {"server_cpu": 2.5, "p50": 3.0, "p99": 3.0}
    assert r.workers_ratio() == 1.5
    assert r.roof_best == {"single": 100.0, "temporal": 100.0, "both": 50.0}
    assert r.targets == [
        "MISSED: causal temporal LiftStream holds 24 cameras at 30 fps with p99 <= 25 ms (target >= 32)",
        "MISSED: server CPU per tracked frame at 8 paced cameras 3.00 ms (target <= 1 ms; the transport's "
        "floor 0.17 ms)",
        "met: server CPU per untracked frame at 8 paced cameras 0.50 ms (target <= 0.6 ms; the transport's "
        "floor 0.17 ms)",
        "met: saturated tracked streams 45 frames/s = 0.90 x both models' per-pose roof (target >= 0.8; "
        "the transport's floor 100 messages/s)",
        "MISSED: saturated tracked streams, the service's workers / one worker = 1.50x (target >= 1.6x)",
        "met: a 16-person frame costs 2.50x a 1-person frame in server CPU (3.00x in p50 latency, 3.00x p99) "
        "(target <= 3x)",
    ]
    markdown = r.markdown()
    assert "| 1 | 100 | 100 | 50 |" in markdown and "x8, tracked, --workers 1" in markdown
    assert "| (echo floor) 8 cameras at 30 fps | 240 | 3.00 | 9.00 | 0 | 0.04 | 0.167 |" in markdown
    assert "| 8 | 240 | 240 | 3.00 | 9.00 | 0 | 0.72 | 3.00 |" in markdown  # CPU ms per frame beside
    assert report([one]).people_ratio() == {} and report([one]).workers_ratio() is None


def test_the_roof_windows_are_a_tracked_persons_causal_windows(lifter: Lifter) -> None:
    contract = Contract("causal", 50.0, 81, 60.0)
    windows = clip_windows(lifter, contract, 5)
    assert windows.poses.shape == (5, contract.slots(30), 17, 3) and np.all(windows.fps == 30)
    np.testing.assert_array_equal(
        windows.poses[0, 0], windows.poses[0, -1]
    )  # frame 0: its own frame repeated
    assert not np.allclose(windows.poses[4, -1], windows.poses[4, -2])  # the person moved


def test_a_tiny_run_measures_every_part_and_writes_its_figures(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "temporal_load.json"
    argv = [
        "--cameras", "1,2", "--refine", "0", "--p99-ms", "10000", "--streams", "1", "--people", "3",
        "--duration", "0.6", "--people-duration", "0.4", "--warmup", "0.3", "--batches", "1,4",
        "--roof-duration", "0.05", "--out", str(out),
    ]  # fmt: skip
    assert main(argv) == 0
    found = json.loads(out.read_text())
    assert [r["name"] for r in found["saturated"]] == [
        "LiftStream x1, 256 in flight, tracked",
        "LiftStream x1, 256 in flight, untracked",
    ]
    assert [r["name"] for r in found["one_worker"]] == ["LiftStream x1, 256 in flight, tracked, --workers 1"]
    assert [r["name"] for r in found["floor"]] == [
        "(echo floor) 8 streams, 256 in flight", "(echo floor) 1 stream, 1 frame in flight",
        "(echo floor) 8 cameras at 30 fps",
    ]  # fmt: skip
    assert found["searched"] == [1, 2] and found["most_cameras"] == 2
    assert [(r["concurrency"], r["extra"]["tracked"]) for r in found["cameras"]] == [
        (1, True), (1, False), (2, True), (2, False),
    ]  # fmt: skip
    assert [r["extra"]["people"] for r in found["people"]] == [1, 1, 1, 3]
    for r in found["saturated"] + found["one_worker"] + found["floor"] + found["cameras"] + found["people"]:
        assert r["errors"] == 0 and r["calls"] > 0 and r["server_cpu"] > 0, r
    assert {r["what"] for r in found["roof"]} == {"session.run", "temporal session.run"}
    assert found["contract"]["slots_30fps"] == 49 and found["roof_end"]
    printed = capsys.readouterr().out
    assert "holds 2 cameras" in printed and "a 3-person frame costs" in printed and "one worker =" in printed
