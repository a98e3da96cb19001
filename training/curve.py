"""Validation accuracy against training time, from a run's history.jsonl (markdown and PNG)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

# Validation figures: val_* in the single-frame trainer's history; <set>_* in the temporal one's
# (repnet.train.temporal_train: sh25, sh50 and gt25 clips).
VALIDATION_PREFIXES = ("val_", "sh25_", "sh50_", "gt25_")


def read_validations(history: Path) -> list[dict[str, float]]:
    """The history records that carry validation figures, in step order."""
    records = [json.loads(line) for line in history.read_text().splitlines() if line.strip()]
    found = (r for r in records if any(k.startswith(VALIDATION_PREFIXES) for k in r))
    return sorted(found, key=lambda r: r["step"])


def figure(record: dict[str, float], key: str) -> float:
    """A validation figure by its name without val_ (nan where the record has none)."""
    return record.get(f"val_{key}", record.get(key, float("nan")))


def markdown_table(records: list[dict[str, float]]) -> str:
    """One row per validation: step, minutes, then every val_* figure (mm)."""
    keys = sorted({k for r in records for k in r if k.startswith(VALIDATION_PREFIXES)})
    lines = [
        "| step | minutes | " + " | ".join(k.removeprefix("val_") for k in keys) + " |",
        "|---:|---:|" + "---:|" * len(keys),
    ]
    for r in records:
        cells = [f"{r[k]:.1f}" if k in r else "" for k in keys]
        lines.append(f"| {r['step']} | {r['minutes']:.1f} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


COMPARED = (
    "gt_pa_mpjpe",
    "gt_mpjpe",
    "gt_mpjpe_ray",
    "gt_symmetry",
    "gt_bone_std",
    "sh_pa_mpjpe",
    "sh_mpjpe",
    "gt_noise_pa_mpjpe",
)


def equal_time_table(runs: dict[str, list[dict[str, float]]], minutes: float) -> str:
    """Each run's last validation at or before `minutes` of wall time, one row per run."""
    lines = [
        "| run | step | minutes | " + " | ".join(COMPARED) + " |",
        "|---|---:|---:|" + "---:|" * len(COMPARED),
    ]
    for name, records in runs.items():
        done = [r for r in records if r["minutes"] <= minutes + 1e-9]
        if not done:
            lines.append(f"| {name} | – | – | " + " | ".join("–" for _ in COMPARED) + " |")
            continue
        r = done[-1]
        cells = [f"{r[f'val_{k}']:.1f}" if f"val_{k}" in r else "–" for k in COMPARED]
        lines.append(f"| {name} | {r['step']} | {r['minutes']:.1f} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def plot(records: list[dict[str, float]], path: Path) -> None:
    """Validation error (Protocol I and II) and skeleton consistency (symmetry, bone length std)
    against wall time, one run."""
    plot_runs({"": records}, path)


PANELS = (
    ("pose error (mm)", ("gt_pa_mpjpe", "gt_mpjpe", "sh_pa_mpjpe", "sh_mpjpe")),
    ("skeleton (mm)", ("gt_symmetry", "gt_bone_std")),
)


def plot_runs(
    runs: dict[str, list[dict[str, float]]], path: Path, figures: tuple[str, ...] | None = None
) -> None:
    """The validation figures of several runs against wall time: one colour per run, one line
    style per figure; left panel pose errors, right panel symmetry and limb bone length std.
    figures: instead, one panel per named figure (e.g. gt_pa_mpjpe), for many runs at once."""
    panels = PANELS if not figures else tuple((key, (key,)) for key in figures)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(panels), figsize=(6 * len(panels), 4.5), squeeze=False)
    styles = ("-", "--", ":", "-.")
    for ax, (ylabel, keys) in zip(axes[0], panels, strict=True):
        for colour, (name, records) in enumerate(runs.items()):
            minutes = [r["minutes"] for r in records]
            for style, key in zip(styles, keys, strict=False):
                values = [figure(r, key) for r in records]
                if all(v != v for v in values):  # no such figure in this run
                    continue
                label = f"{name}: {key}" if name else key
                colour_name = f"C{colour % 10}"
                style = style if colour < 10 else ("--", ":", "-.")[(colour // 10 - 1) % 3]
                ax.plot(minutes, values, style, marker="o", ms=3, color=colour_name, label=label)
        ax.set_xlabel("training wall time (min)")
        ax.set_ylabel(f"validation {ylabel}")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(
        "RepNet validation on held-out training-subject frames (gt: GT 2D, sh: SH detections;"
        " 25/50: clips at 25 Hz / upsampled to 50 Hz)"
    )
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    """python -m repnet.train.curve: tables and figures of runs' validation histories."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument(
        "--history",
        nargs="+",
        required=True,
        help="runs/<name>/history.jsonl, or several as NAME=PATH to draw them side by side",
    )
    parser.add_argument("--png", type=Path, help="write the curve here")
    parser.add_argument("--at-minutes", type=float, help="also compare the runs at this wall time")
    parser.add_argument(
        "--figures", nargs="+", help="plot one panel per figure, e.g. gt_pa_mpjpe gt_symmetry"
    )
    args = parser.parse_args(argv)
    runs = {}
    for item in args.history:
        name, _, path = item.rpartition("=")
        runs[name] = read_validations(Path(path))
    for name, records in runs.items():
        print(f"{name or args.history[0]}:\n{markdown_table(records)}\n")
    if args.at_minutes is not None:
        print(f"at {args.at_minutes:g} min of wall time:\n{equal_time_table(runs, args.at_minutes)}")
    if args.png:
        plot_runs(runs, args.png, tuple(args.figures) if args.figures else None)


if __name__ == "__main__":
    main()
