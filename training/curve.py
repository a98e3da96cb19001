"""Validation accuracy against training time, from a run's history.jsonl (markdown and PNG)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def read_validations(history: Path) -> list[dict[str, float]]:
    """The history records that carry validation figures, in step order."""
    records = [json.loads(line) for line in history.read_text().splitlines() if line.strip()]
    return sorted((r for r in records if any(k.startswith("val_") for k in r)), key=lambda r: r["step"])


def markdown_table(records: list[dict[str, float]]) -> str:
    """One row per validation: step, minutes, then every val_* figure (mm)."""
    keys = sorted({k for r in records for k in r if k.startswith("val_")})
    lines = [
        "| step | minutes | " + " | ".join(k.removeprefix("val_") for k in keys) + " |",
        "|---:|---:|" + "---:|" * len(keys),
    ]
    for r in records:
        cells = [f"{r[k]:.1f}" if k in r else "" for k in keys]
        lines.append(f"| {r['step']} | {r['minutes']:.1f} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def plot(records: list[dict[str, float]], path: Path) -> None:
    """Validation MPJPE (Protocol I and II) against wall time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    minutes = [r["minutes"] for r in records]
    for key in sorted({k for r in records for k in r if k.startswith("val_") and "symmetry" not in k}):
        values = [r.get(key, float("nan")) for r in records]
        ax.plot(minutes, values, marker="o", label=key.removeprefix("val_"))
    ax.set_xlabel("training wall time (min)")
    ax.set_ylabel("validation error (mm)")
    ax.set_title("RepNet validation on held-out training-subject frames")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--history", type=Path, required=True, help="runs/<name>/history.jsonl")
    parser.add_argument("--png", type=Path, help="write the curve here")
    args = parser.parse_args(argv)
    records = read_validations(args.history)
    print(markdown_table(records))
    if args.png:
        plot(records, args.png)


if __name__ == "__main__":
    main()
