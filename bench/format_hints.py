"""How well the service tells a pose sent without its format which format it looks like.

    python -m bench.format_hints [--frame-step 10] [--out runs/bench/format_hints.json]

Human3.6M S9/S11 ground truth, projected through the true cameras to 2D, is turned into each
detector format (repnet.core.formats.from_model_joints: the joints a format shares with Human3.6M; eyes,
ears, feet and hands missing) and sent through the service's input rules (keypoints.prepare_poses):

- without a format (the request's default, h36m17): a pose of any other count than 17 should be
  refused with the hint naming its format ("looks like mpii16", "coco18", ...; 25 joints: "body25 or
  body25b", the two formats of that count, which nothing in the joints tells apart) (target >= 99 %);
- 17-joint poses under a label of another joint count (mpii16): the hint must tell h36m17 from
  coco17 by the geometry (joint 0 above the shoulders: COCO's nose);
- a coco17 pose without a format has the default's joint count, so no count hint: the reply's format
  warning (repnet.core.lookalike) should say it looks like coco17 (the model is run for it);
- every pose under its own label: no hint and no format warning (target: none).
"""

from __future__ import annotations

import argparse
import json
import logging
import re
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

if __package__ in (None, ""):  # `python bench/format_hints.py`
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench.format_mixup import frames
from bench.h36m_args import check_frame_step, h36m_parser
from repnet.core.format_hints import formats_with
from repnet.core.formats import DEFAULT_FORMAT, FORMATS, from_model_joints
from repnet.core.inputs import PoseInput
from repnet.core.keypoints import prepare_poses
from repnet.runtime.lifter import Lifter
from repnet.runtime.replies import build_replies
from repnet.server.app import limits_of, load_lifter
from repnet.server.config import Settings
from repnet.train import data
from repnet.train.testset import DATASET_LABEL, build_test_set, select_sequences

log = logging.getLogger("bench.format_hints")
BATCH = 4096
# Formats whose joint count the count hint answers (17 is the default's: the format warning's case).
COUNT_HINTED = tuple(name for name, f in FORMATS.items() if len(f.joint_names) != 17)


def count_answer(name: str) -> str:
    """What the count hint should say for a pose in `name`: every format with its joint count."""
    return " or ".join(formats_with(len(FORMATS[name].joint_names)))


def hints(points: np.ndarray, present: np.ndarray, label: str) -> list[str]:
    """Per pose, the format(s) its refusal says to send ("coco18", "body25 or body25b"; "" when none:
    accepted or no hint)."""
    limits = limits_of(Settings())
    out: list[str] = []
    for a in range(0, len(points), BATCH):
        chunk = zip(points[a : a + BATCH], present[a : a + BATCH], strict=True)
        prepared = prepare_poses([PoseInput(p, v, None, label) for p, v in chunk], limits)
        for found in prepared.violations:
            said = [
                " or ".join(re.findall(r'"(\w+)"', v.reason.split("send format ")[1]))
                for v in found
                if "looks like " in v.reason
            ]
            out.append(said[0] if said else "")
    return out


def warned(lifter: Lifter, points: np.ndarray, present: np.ndarray, label: str) -> list[str]:
    """Per pose, the format the reply's format warning names ("" when none)."""
    limits = limits_of(Settings())
    out: list[str] = []
    for a in range(0, len(points), BATCH):
        chunk = zip(points[a : a + BATCH], present[a : a + BATCH], strict=True)
        inputs = prepare_poses([PoseInput(p, v, None, label) for p, v in chunk], limits).check()
        replies = build_replies(inputs, lifter.lift(inputs.keypoints_2d, inputs.visible))
        for pose_warnings in replies.columns["warnings"]:
            said = [w.split("look like ")[1].split(",")[0] for w in pose_warnings if "look like " in w]
            out.append(said[0] if said else "")
    return out


def row(case: str, truth: str, label: str, said: list[str], want: str) -> dict[str, Any]:
    """One measured case: how many poses were told `want` (the right answer; "" = nothing)."""
    told = np.array(said)
    return {
        "case": case,
        "truth": truth,
        "sent_as": label,
        "poses": len(told),
        "right": float((told == want).mean()),
        "right_count": int((told == want).sum()),
        "told_other": sorted({str(t) for t in told if t != want}),
    }


def run(args: argparse.Namespace) -> dict[str, Any]:
    """Every format's poses without a format, under a wrong count's label and under their own."""
    started = time.perf_counter()
    data_dir = data.resolve_data_dir(args.data_dir)
    poses = select_sequences(data.load_poses(data_dir, "test"), list(data.TEST_SUBJECTS), [])
    test = build_test_set(poses, data.load_cameras(data_dir), None, args.frame_step)
    points_2d = test.points.astype(np.float32)  # (M, 17, 2) px, distorted GT projections
    lifter = load_lifter(Settings(model_path=args.model, intra_op_threads=args.threads))
    log.info("%d poses from %d camera sequences", len(points_2d), test.sequences)
    rows = []
    for name in FORMATS:
        points, present = from_model_joints(FORMATS[name], points_2d)
        points = points.astype(np.float64)
        log.info("%s", name)
        if name in COUNT_HINTED:
            said = hints(points, present, DEFAULT_FORMAT)
            rows.append(row("no format", name, DEFAULT_FORMAT, said, count_answer(name)))
        elif name == "coco17":
            rows.append(
                row("no format", name, DEFAULT_FORMAT, warned(lifter, points, present, DEFAULT_FORMAT), name)
            )
        if len(FORMATS[name].joint_names) == 17:
            rows.append(row("other count's label", name, "mpii16", hints(points, present, "mpii16"), name))
        rows.append(row("own label: no hint", name, name, hints(points, present, name), ""))
        if len(FORMATS[name].joint_names) == 17:
            rows.append(row("own label: no warning", name, name, warned(lifter, points, present, name), ""))
    hinted = [r for r in rows if r["case"] == "no format" and r["truth"] in COUNT_HINTED]
    right_labels = [r for r in rows if r["case"].startswith("own label")]
    return {
        "command": " ".join(["python -m bench.format_hints", *sys.argv[1:]]),
        "dataset": f"Human3.6M {DATASET_LABEL}, ground-truth 2D (true cameras), all 4 cameras",
        "frame_step": args.frame_step,
        "model_id": lifter.info.model_id,
        "poses_per_format": len(points_2d),
        "rows": rows,
        "summary": {
            "count_hint_right": sum(r["right_count"] for r in hinted) / sum(r["poses"] for r in hinted),
            "right_labels_told_something": 1
            - sum(r["right_count"] for r in right_labels) / sum(r["poses"] for r in right_labels),
        },
        "wall_time_s": round(time.perf_counter() - started, 1),
    }


def markdown(result: dict[str, Any]) -> str:
    """The result as a markdown table."""
    s = result["summary"]
    lines = [
        f"`{result['command']}`: {result['dataset']}, {frames(result['frame_step'])} "
        f"({result['poses_per_format']:,} poses per format), model `{result['model_id']}`.",
        "",
        "| case | poses in | sent as | poses | told the right thing | told otherwise |",
        "|---|---|---|---:|---:|---|",
    ]
    for r in result["rows"]:
        other = ", ".join(t or "nothing" for t in r["told_other"]) or "—"
        lines.append(
            f"| {r['case']} | {r['truth']} | {r['sent_as']} | {r['poses']:,} "
            f"| {r['right']:.3%} ({r['right_count']:,}) | {other} |"
        )
    lines += [
        "",
        "Poses of another count than 17 without a format told the right format(s): "
        f"{s['count_hint_right']:.3%} "
        f"(target >= 99 %); correctly labelled poses told anything: {s['right_labels_told_something']:.3%} "
        "(target: none).",
    ]
    return "\n".join(lines)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line of `python -m bench.format_hints`."""
    parser = h36m_parser("format_hints", __doc__)
    parser.add_argument("--frame-step", type=int, default=10, help="use every n-th frame (default 10)")
    parser.add_argument("--out", type=Path, default=Path("runs/bench/format_hints.json"))
    args = parser.parse_args(argv)
    check_frame_step(parser, args)
    return args


def main(argv: list[str] | None = None) -> int:
    """Run, print the markdown and write the JSON; the exit status."""
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    args = parse_args(argv)
    result = run(args)
    print(markdown(result))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
