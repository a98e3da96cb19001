"""Markdown tables, JSON and the per-action bar chart of a repnet.train.evaluate result."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

SUBSET_LABELS = {"all": "all sequences", "without_misaligned": "without misaligned S9"}
DASH = "–"
# (header, key in metrics.summarize) of the overall table after "test set" and "poses".
OVERALL_COLUMNS = (
    ("MPJPE P-I", "mpjpe"),
    ("median", "mpjpe_median"),
    ("P-I ray", "mpjpe_ray"),
    ("PA-MPJPE P-II", "pa_mpjpe"),
    ("median", "pa_mpjpe_median"),
    ("PCK3D", "pck3d_150"),
    ("AUC", "auc"),
    ("PA-PCK3D", "pa_pck3d_150"),
    ("PA-AUC", "pa_auc"),
    ("symmetry mean", "symmetry_mean"),
    ("std", "symmetry_std"),
    ("max", "symmetry_max"),
)
ROBUSTNESS_HEADER = [
    "P-I",
    "P-I ray",
    "P-II",
    "P-I w/o misaligned",
    "P-II w/o misaligned",
    "symmetry",
    "paper P-II",
]
PER_ACTION_HEADER = [
    "action",
    "poses",
    "MPJPE P-I",
    "P-I ray",
    "PA-MPJPE P-II",
    "P-I w/o misaligned",
    "P-II w/o misaligned",
    "PCK3D",
    "AUC",
    "symmetry",
]


def _fmt(value: float | None, digits: int = 1) -> str:
    return DASH if value is None else f"{value:.{digits}f}"


def _table(header: list[str], rows: list[list[str]]) -> list[str]:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    return lines + ["| " + " | ".join(row) + " |" for row in rows]


def _row(label: str, poses: str, figures: dict[str, float], digits: int = 1) -> list[str]:
    """A row of the overall table; figures lacking a column's key show a dash."""
    return [label, poses] + [_fmt(figures.get(key), digits) for _, key in OVERALL_COLUMNS]


def _overall_rows(result: dict[str, Any]) -> list[list[str]]:
    rows = []
    for subset, label in SUBSET_LABELS.items():
        res = result[subset]
        rows.append(_row(f"{label}, all frames", f"{res['overall']['poses']:,}", res["overall"]))
        actions = f"{len(res['per_action'])} actions"
        rows.append(_row(f"{label}, mean over actions", actions, res["mean_over_actions"]))
    overall = result["all"]["overall"]
    gt = {key: overall[f"gt_{key}"] for key in ("symmetry_mean", "symmetry_std", "symmetry_max")}
    rows.append(_row("ground truth (own symmetry)", f"{overall['poses']:,}", gt, digits=2))
    if "off_axis" in result:  # evaluations written before it have no such row
        floor = {"mpjpe": result["off_axis"]["mpjpe"]}
        rows.append(_row("exact pose and view, no intrinsics (P-I floor)", f"{overall['poses']:,}", floor))
    paper = {key: result["paper"][key] for key in ("mpjpe", "pa_mpjpe", "symmetry_mean")}
    rows.append(_row("RepNet paper (GT 2D)", DASH, paper))
    return rows


def _per_action_rows(result: dict[str, Any]) -> list[list[str]]:
    rows = []
    for action, a in result["all"]["per_action"].items():
        b = result["without_misaligned"]["per_action"].get(action, {})
        values = [
            a["mpjpe"],
            a.get("mpjpe_ray"),
            a["pa_mpjpe"],
            b.get("mpjpe"),
            b.get("pa_mpjpe"),
            a["pck3d_150"],
            a["auc"],
        ]
        rows.append([action, f"{a['poses']:,}", *map(_fmt, values), _fmt(a["symmetry_mean"])])
    return rows


def _robustness_rows(rows: list[dict[str, Any]], key: str, paper: dict[float, float]) -> list[list[str]]:
    out = []
    for row in rows:
        full, aligned = row["all"], row["without_misaligned"]
        values = [
            full["mpjpe"],
            full.get("mpjpe_ray"),
            full["pa_mpjpe"],
            aligned["mpjpe"],
            aligned["pa_mpjpe"],
            full.get("symmetry"),
            paper.get(row[key]),
        ]
        out.append([f"{row[key]:g}", *map(_fmt, values)])
    return out


def render_markdown(result: dict[str, Any]) -> str:
    """The evaluation as markdown: overall, per-action, noise and occlusion tables."""
    overall_header = ["test set", "poses", *(header for header, _ in OVERALL_COLUMNS)]
    lines = [
        f"## RepNet evaluation on {result['dataset']}",
        "",
        f"Model `{result['model']}` (model_id `{result['model_id']}`), 2D inputs: {result['inputs']}; "
        f"subjects {' '.join(result['subjects'])}, {len(result['cameras'])} cameras, frame step "
        f"{result['frame_step']}: {result['all']['overall']['poses']:,} poses from "
        f"{result['sequences']} camera sequences, {len(result['skipped_sequences'])} skipped "
        "(no detections). Without misaligned: " + ", ".join(result["misaligned_sequences"]) + " left out.",
        "",
        "Protocol I (P-I): `pose_3d` rotated into the camera frame by the rotation of `camera`, "
        "root-aligned, against the camera-frame ground truth. P-I ray: the same, turned first by the "
        "ray from the camera to the centroid of the visible joints (the camera's intrinsics known): "
        "K is the view along that ray, since the normalised input no longer shows where in the image "
        "the person stood. The P-I floor is the plain P-I of a lifter whose pose and view along "
        "that ray are both exact: no lifter of centred 2D inputs without the intrinsics does better. "
        "Protocol II (P-II): per-pose "
        "Procrustes (similarity) alignment. Medians of per-pose errors; PCK3D at 150 mm, AUC over "
        "0-150 mm. Symmetry error: sum of |left - right| arm and leg bone lengths (mm).",
        "",
        "### Overall (mm; PCK3D and AUC in %)",
        "",
        *_table(overall_header, _overall_rows(result)),
        "",
        "### Per action (mm)",
        "",
        *_table(PER_ACTION_HEADER, _per_action_rows(result)),
    ]
    bones = result.get("bone_lengths")
    if bones:
        lines += [
            "",
            "### Limb bone lengths: std over the frames of one subject, mean over subjects (mm)",
            "",
            *_table(
                ["", "mean over the 8 arm and leg bones", "largest", *bones["per_bone_std"]],
                [
                    [
                        "prediction",
                        _fmt(bones["mean_std"]),
                        _fmt(bones["max_std"]),
                        *(_fmt(v) for v in bones["per_bone_std"].values()),
                    ],
                    [
                        "ground truth",
                        _fmt(bones["gt_mean_std"]),
                        _fmt(bones["gt_max_std"]),
                        *(DASH for _ in bones["per_bone_std"]),
                    ],
                ],
            ),
        ]
    tables = result.get("tables")
    if tables:
        subset = f"GT 2D, frame step {tables['frame_step']}, {tables['poses']:,} poses, seed {result['seed']}"
        scale = result.get("paper_noise_scale", 1.0)
        noise_paper = {10.0 * scale: result["paper"]["noise_10_pa_mpjpe"]}
        lines += [
            "",
            f"### Noise: GT 2D + N(0, σ) px ({subset})",
            "",
            f"The paper adds σ = 10 px to people at most ~200 px tall; in Human3.6M's native pixels, used "
            f"here, a person is up to ~420 px tall (median 327), so the paper's σ = 10 px is our "
            f"σ = {10 * scale:g} px, and its P-II stands in that row. Both rows are reported.",
            "",
            *_table(
                ["σ (px)", *ROBUSTNESS_HEADER], _robustness_rows(tables["noise"], "sigma_px", noise_paper)
            ),
            "",
            f"### Occlusion: random non-root joints hidden, visibility 0 ({subset})",
            "",
            *_table(
                ["hidden joints", *ROBUSTNESS_HEADER],
                _robustness_rows(tables["occlusion"], "masked_joints", {}),
            ),
        ]
    deciles = {"GT 2D, all frames": result.get("plausibility_deciles")}
    spearman = {"GT 2D, all frames": result.get("plausibility_spearman")}
    for name, rows in (tables or {}).get("plausibility_deciles", {}).items():
        sigma = name.removeprefix("noise_").removesuffix("px")
        if sigma != "0":
            label = f"GT 2D + N(0, {sigma} px), frame step {tables['frame_step']}"  # type: ignore[index]
            deciles[label] = rows
            spearman[label] = tables.get("plausibility_spearman", {}).get(name)  # type: ignore[union-attr]
    if deciles["GT 2D, all frames"]:
        lines += [
            "",
            "### P-II by plausibility decile (mm): decile 1 holds the poses the critic finds least plausible",
        ]
        for label, rows in deciles.items():
            rho = spearman[label]
            ranked = "" if rho is None else f" (Spearman rank correlation with P-II {rho:+.3f})"
            lines += [
                "",
                f"{label}{ranked}:",
                "",
                *_table(
                    ["decile", "poses", "plausibility", "P-II", "symmetry"],
                    [
                        [
                            str(r["decile"]),
                            f"{r['poses']:,}",
                            f"{r['plausibility_min']:.3f}-{r['plausibility_max']:.3f}",
                            _fmt(r["pa_mpjpe"]),
                            _fmt(r["symmetry"]),
                        ]
                        for r in rows or []
                    ],
                ),
            ]
    if result["notes"]:
        lines += ["", "Notes: " + "; ".join(result["notes"])]
    return "\n".join(lines) + "\n"


def plot_per_action(result: dict[str, Any], path: Path) -> None:
    """Grouped bars of P-I and P-II MPJPE per action, with and without the misaligned sequences."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    actions = list(result["all"]["per_action"])
    x = np.arange(len(actions))
    series = [
        ("P-I, all", "all", "mpjpe", "#1f77b4"),
        ("P-I, w/o misaligned", "without_misaligned", "mpjpe", "#aec7e8"),
        ("P-II, all", "all", "pa_mpjpe", "#d62728"),
        ("P-II, w/o misaligned", "without_misaligned", "pa_mpjpe", "#ff9896"),
    ]
    width = 0.2
    fig, ax = plt.subplots(figsize=(max(8.0, 0.8 * len(actions) + 2), 4.8))
    top = result["paper"]["mpjpe"]
    for i, (label, subset, key, color) in enumerate(series):
        per_action = result[subset]["per_action"]
        values = [per_action[a][key] if a in per_action else np.nan for a in actions]
        ax.bar(x + (i - 1.5) * width, values, width, label=label, color=color)
        top = max(top, float(np.nanmax(values)))
    ax.axhline(result["paper"]["mpjpe"], color="#1f77b4", ls="--", lw=1, label="paper P-I (GT 2D)")
    ax.axhline(result["paper"]["pa_mpjpe"], color="#d62728", ls="--", lw=1, label="paper P-II (GT 2D)")
    ax.set_ylim(0, top * 1.3)  # headroom for the legend
    ax.set_xticks(x, actions, rotation=40, ha="right")
    ax.set_ylabel("error (mm)")
    ax.set_title(f"{result['model']} on {result['dataset']}, 2D: {result['inputs']}", fontsize=10)
    ax.legend(fontsize=8, ncol=3, loc="upper center")
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _rounded(value: Any, digits: int = 3) -> Any:
    """The result with every float rounded, for a compact JSON."""
    if isinstance(value, float):
        return round(value, digits)
    if isinstance(value, dict):
        return {k: _rounded(v, digits) for k, v in value.items()}
    if isinstance(value, list):
        return [_rounded(v, digits) for v in value]
    return value


def write_report(result: dict[str, Any], out_dir: Path) -> str:
    """Write evaluation.json, evaluation.md and per_action.png to out_dir; returns the markdown."""
    out_dir.mkdir(parents=True, exist_ok=True)
    markdown = render_markdown(result)
    (out_dir / "evaluation.json").write_text(json.dumps(_rounded(result), indent=1) + "\n")
    (out_dir / "evaluation.md").write_text(markdown)
    plot_per_action(result, out_dir / "per_action.png")
    return markdown
