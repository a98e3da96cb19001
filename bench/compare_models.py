"""Serving cost of two or more models side by side: the roof (bench.roof) of each, alternating.

    python -m bench.compare_models --models runs/model_v3/repnet-h36m.onnx service/models/repnet-h36m.onnx

Each round measures every model once, in order, so a machine that gets busier or quieter during
the run weighs on all of them alike; the table gives every round's figure, not a mean that would
hide the spread. Raw onnxruntime through the service's own session options (`session.run`) and
the service's Lifter around it (`Lifter.lift`), at the batch sizes given.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

if __package__ in (None, ""):  # `python bench/compare_models.py`
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench.roof import RoofRow, measure_roof
from bench.stats import write_json
from repnet.server.app import load_lifter
from repnet.server.config import Settings


def compare(
    models: list[Path], batches: tuple[int, ...], rounds: int, duration: float, threads: int
) -> dict[str, list[list[RoofRow]]]:
    """{model path: one list of roof rows per round}, the models measured in turn each round."""
    results: dict[str, list[list[RoofRow]]] = {str(m): [] for m in models}
    for _ in range(rounds):
        for model in models:
            settings = Settings(model_path=model, intra_op_threads=threads)
            results[str(model)].append(measure_roof(settings, batches, duration))
    return results


def table(results: dict[str, list[list[RoofRow]]]) -> str:
    """Markdown: one row per model, one column per (call, batch), every round's figure."""
    first = next(iter(results.values()))[0]
    columns = [(row.what, row.batch) for row in first]

    def cell(rows: list[RoofRow], what: str, batch: int) -> str:
        row = next(r for r in rows if (r.what, r.batch) == (what, batch))
        return f"{row.ms_per_call:.2f} ms" if batch == 1 else f"{row.frames_per_s:,.0f} poses/s"

    lines = [
        "| model | " + " | ".join(f"{what} batch {batch}" for what, batch in columns) + " |",
        "|---|" + "---:|" * len(columns),
    ]
    for model, rounds in results.items():
        model_id = load_lifter(Settings(model_path=Path(model))).info.model_id
        cells = [" / ".join(cell(rows, what, batch) for rows in rounds) for what, batch in columns]
        lines.append(f"| {model_id} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    """Measure the given models in turn and print the table (and write JSON with --out)."""
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--models", type=Path, nargs="+", required=True)
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 1024])
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--duration", type=float, default=3.0, help="seconds per measurement")
    parser.add_argument("--threads", type=int, default=0, help="intra-op threads (0: the service's default)")
    parser.add_argument("--out", type=Path, help="also write the rows as JSON")
    args = parser.parse_args(argv)
    results = compare(args.models, tuple(args.batches), args.rounds, args.duration, args.threads)
    print(table(results))
    if args.out:
        write_json(args.out, results)
        print(json.dumps({"wrote": str(args.out)}))


if __name__ == "__main__":
    main()
