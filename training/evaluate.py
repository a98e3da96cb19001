"""Evaluation CLI: Protocol I/II, PCK3D, AUC, symmetry, noise and occlusion tables on Human3.6M S9/S11."""

from __future__ import annotations

import argparse
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import onnxruntime as ort
from tqdm import tqdm

from repnet.core import geometry, skeleton
from repnet.train import data, metrics, report
from repnet.train.testset import DATASET_LABEL, TestSet, build_test_set, select_sequences

log = logging.getLogger(__name__)

PAPER = {"mpjpe": 50.9, "pa_mpjpe": 38.2, "symmetry_mean": 8.2, "noise_10_pa_mpjpe": 74.9}
# The paper's noise table adds sigma = 10 px to people at most ~200 px tall; in Human3.6M's
# native pixels (used here) a person is up to ~420 px tall (median 327), so its sigma = 10
# corresponds to our 20 px.
PAPER_NOISE_SCALE = 2.0
NOISE_SIGMAS_PX: tuple[float, ...] = (5.0, 10.0, 15.0, 20.0, 40.0)
PLAUSIBILITY_NOISE_PX: tuple[float, ...] = (20.0, 40.0)  # noisy inputs of the P-II-by-plausibility tables
OCCLUDED_COUNTS: tuple[int, ...] = (1, 2, 3)

# (points, visible) -> (pose_3d, camera, plausibility or None)
Lift = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray | None]]


@dataclass(frozen=True)
class Scores:
    """Per-frame errors of one pass over a TestSet."""

    p1: np.ndarray  # (M, 17) Protocol I joint errors, mm
    p1_ray: np.ndarray  # (M, 17) Protocol I turned along the ray to the person (intrinsics known), mm
    p2: np.ndarray  # (M, 17) Protocol II joint errors, mm
    symmetry: np.ndarray  # (M,) symmetry error of the predicted pose, mm
    limbs: np.ndarray  # (M, 8) lengths of the predicted arm and leg bones (metrics.LIMB_BONES), mm
    plausibility: np.ndarray | None  # (M,) the model's plausibility output, if it has one


def open_model(path: Path, threads: int = 0) -> tuple[Lift, dict[str, str]]:
    """An onnxruntime lifting function for a model with the ONNX contract, and its metadata."""
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    session = ort.InferenceSession(str(path), options, providers=ort.get_available_providers())
    inputs = sorted(i.name for i in session.get_inputs())
    outputs = {o.name for o in session.get_outputs()}
    if inputs != ["keypoints_2d", "visibility"] or not {"pose_3d", "camera"} <= outputs:
        raise ValueError(
            f"{path}: expected inputs keypoints_2d, visibility and outputs pose_3d, camera; "
            f"got inputs {inputs} and outputs {sorted(outputs)}"
        )
    meta = dict(session.get_modelmeta().custom_metadata_map)
    if meta.get("skeleton", "h36m17") != "h36m17":
        raise ValueError(f"{path}: expected skeleton h36m17, got {meta['skeleton']}")

    names = ["pose_3d", "camera"] + (["plausibility"] if "plausibility" in outputs else [])

    def lift(points: np.ndarray, visible: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        values = session.run(names, {"keypoints_2d": points, "visibility": visible})
        return values[0], values[1], values[2] if len(values) > 2 else None

    return lift, meta


def score(
    lift: Lift, points: np.ndarray, visible: np.ndarray, test: TestSet, batch_size: int, desc: str
) -> Scores:
    """Lift (M, 17, 2) points in batches and score them against the camera-frame GT of `test`
    (whose intrinsics give Protocol I along the ray to the person)."""
    gt = test.gt
    p1, p1_ray, p2, sym, limbs, plaus = [], [], [], [], [], []
    with tqdm(total=len(points), desc=desc, unit="pose", unit_scale=True, leave=False) as bar:
        for start in range(0, len(points), batch_size):
            batch = slice(start, start + batch_size)
            pose, camera, plausibility = lift(points[batch], visible[batch])  # (n, 17, 3), (n, 2, 3), (n,)
            ray = geometry.ray_turn(points[batch], visible[batch], test.focal[batch], test.centre[batch])
            pose_cam, pose_ray = metrics.camera_frames(pose, camera, ray)  # Protocol I, and along the ray
            p1.append(metrics.joint_errors(pose_cam, gt[batch]).astype(np.float32))
            p1_ray.append(metrics.joint_errors(pose_ray, gt[batch]).astype(np.float32))
            p2.append(metrics.procrustes_errors(pose, gt[batch]).astype(np.float32))
            sym.append(metrics.symmetry_error(pose).astype(np.float32))
            limbs.append(metrics.segment_lengths(pose, metrics.LIMB_BONES).astype(np.float32))
            if plausibility is not None:
                plaus.append(plausibility.astype(np.float32))
            bar.update(len(pose))
    return Scores(
        np.concatenate(p1),
        np.concatenate(p1_ray),
        np.concatenate(p2),
        np.concatenate(sym),
        np.concatenate(limbs),
        np.concatenate(plaus) if plaus else None,
    )


def bone_length_figures(scores: Scores, test: TestSet) -> dict[str, Any]:
    """Std of each arm and leg bone's length over the frames of one subject, averaged over the
    subjects (one person's bones keep their length), for the predictions and the ground truth."""
    gt_limbs = metrics.segment_lengths(test.gt, metrics.LIMB_BONES)

    def per_bone(lengths: np.ndarray) -> np.ndarray:
        return np.mean([lengths[test.subject == i].std(axis=0) for i in range(len(test.subjects))], axis=0)

    pred, gt = per_bone(scores.limbs), per_bone(gt_limbs)
    names = [f"{skeleton.JOINT_NAMES[a]}-{skeleton.JOINT_NAMES[b]}" for a, b in metrics.LIMB_BONES]
    return {
        "mean_std": float(pred.mean()),
        "max_std": float(pred.max()),
        "gt_mean_std": float(gt.mean()),
        "gt_max_std": float(gt.max()),
        "per_bone_std": dict(zip(names, map(float, pred), strict=True)),
    }


def off_axis_floor(test: TestSet) -> dict[str, float]:
    """The plain P-I (mm) of a lifter whose pose and view along the ray are exact, over all frames
    (metrics.off_axis_errors), and how far off the optical axis the people stand (degrees)."""
    ray = geometry.ray_turn(test.points, test.visible, test.focal, test.centre)
    errors, angles = metrics.off_axis_errors(test.gt, ray)
    return {
        "mpjpe": float(errors.mean()),
        "angle_mean_deg": float(angles.mean()),
        "angle_max_deg": float(angles.max()),
    }


def plausibility_spearman(scores: Scores) -> float:
    """Spearman's rank correlation of the plausibility output and the per-pose P-II: below 0 when
    a lower score goes with a larger error."""
    assert scores.plausibility is not None
    return metrics.spearman(scores.plausibility, scores.p2.mean(axis=1))


def plausibility_deciles(scores: Scores) -> list[dict[str, float]]:
    """P-II by decile of the plausibility output: does a low score flag a bad pose?"""
    assert scores.plausibility is not None
    order = np.argsort(scores.plausibility, kind="stable")
    pose_p2 = scores.p2.mean(axis=1)
    rows = []
    for i, idx in enumerate(np.array_split(order, 10)):
        rows.append(
            {
                "decile": i + 1,
                "poses": int(len(idx)),
                "plausibility_min": float(scores.plausibility[idx].min()),
                "plausibility_max": float(scores.plausibility[idx].max()),
                "pa_mpjpe": float(pose_p2[idx].mean()),
                "symmetry": float(scores.symmetry[idx].mean()),
            }
        )
    return rows


def subset_masks(test: TestSet) -> dict[str, np.ndarray]:
    """All test frames, and those outside the three misaligned S9 sequences."""
    return {"all": np.ones(len(test.gt), dtype=bool), "without_misaligned": ~test.misaligned}


def summarize_scores(scores: Scores, test: TestSet) -> dict[str, Any]:
    """Overall (all frames), mean over actions and per-action figures for each subset."""
    gt_symmetry = metrics.symmetry_error(test.gt)
    out: dict[str, Any] = {}
    for subset, mask in subset_masks(test).items():

        def figures(m: np.ndarray) -> dict[str, float]:
            return metrics.summarize(
                scores.p1[m], scores.p2[m], scores.symmetry[m], gt_symmetry[m], scores.p1_ray[m]
            )

        per_action = {
            name: figures(mask & (test.action == i))
            for i, name in enumerate(test.actions)
            if (mask & (test.action == i)).any()
        }
        out[subset] = {
            "overall": figures(mask),
            "mean_over_actions": {
                key: float(np.mean([a[key] for a in per_action.values()]))
                for key in ("mpjpe", "mpjpe_ray", "pa_mpjpe")
            },
            "per_action": per_action,
        }
    return out


def robustness_tables(
    lift: Lift, test: TestSet, batch_size: int, seed: int
) -> dict[str, list[dict[str, Any]]]:
    """Noise (GT + N(0, sigma) px) and occlusion (k random non-root joints hidden) rows."""
    masks = subset_masks(test)

    scored: dict[float, Scores] = {}  # the noise rows' scores by sigma, for the plausibility deciles

    def row(points: np.ndarray, visible: np.ndarray, desc: str, sigma: float | None = None) -> dict[str, Any]:
        s = score(lift, points, visible, test, batch_size, desc)
        if sigma is not None:
            scored[sigma] = s
        return {
            name: {
                "mpjpe": float(s.p1[m].mean()),
                "mpjpe_ray": float(s.p1_ray[m].mean()),
                "pa_mpjpe": float(s.p2[m].mean()),
                "symmetry": float(s.symmetry[m].mean()),
            }
            for name, m in masks.items()
        }

    noise = [{"sigma_px": 0.0, **row(test.points, test.visible, "noise 0px", 0.0)}]
    for i, sigma in enumerate(NOISE_SIGMAS_PX):
        rng = np.random.default_rng([seed, 1, i])
        noisy = (test.points + rng.normal(0.0, sigma, test.points.shape)).astype(np.float32)
        noise.append({"sigma_px": sigma, **row(noisy, test.visible, f"noise {sigma:g}px", sigma)})
    occlusion = [{"masked_joints": 0, **{k: v for k, v in noise[0].items() if k != "sigma_px"}}]
    for i, count in enumerate(OCCLUDED_COUNTS):
        rng = np.random.default_rng([seed, 2, i])
        points, visible = data.hide_random_joints(test.points, test.visible, count, rng)
        occlusion.append({"masked_joints": count, **row(points, visible, f"occlusion {count}")})
    tables: dict[str, Any] = {"noise": noise, "occlusion": occlusion}
    if scored[0.0].plausibility is not None:
        sigmas = (0.0, *PLAUSIBILITY_NOISE_PX)
        tables["plausibility_deciles"] = {f"noise_{s:g}px": plausibility_deciles(scored[s]) for s in sigmas}
        tables["plausibility_spearman"] = {f"noise_{s:g}px": plausibility_spearman(scored[s]) for s in sigmas}
    return tables


def _restriction(args: argparse.Namespace) -> str:
    """' (subset: ...)' when the CLI narrowed the test set, else ''."""
    parts = [f"subjects {' '.join(args.subjects)}"] if set(args.subjects) != set(data.TEST_SUBJECTS) else []
    parts += [f"actions {' '.join(args.actions)}"] if args.actions else []
    parts += [f"cameras {' '.join(args.cameras)}"] if set(args.cameras) != set(data.CAMERAS) else []
    return f" (subset: {'; '.join(parts)})" if parts else ""


def evaluate(args: argparse.Namespace) -> dict[str, Any]:
    """Run the whole evaluation described by the CLI arguments; returns the results dict."""
    started = time.perf_counter()
    data_dir = data.resolve_data_dir(args.data_dir)
    poses = select_sequences(data.load_poses(data_dir, "test"), args.subjects, args.actions)
    cameras = data.load_cameras(data_dir)
    unknown = sorted({c for c in args.cameras if any(c not in cameras[k.split("/")[0]] for k in poses)})
    if unknown:
        raise ValueError(f"--cameras: no calibration for {unknown} in {data_dir / 'cameras.json'}")
    detections = None if args.inputs == "gt" else data.load_detections(Path(args.inputs))
    lift, meta = open_model(args.model, args.threads)
    test = build_test_set(poses, cameras, detections, args.frame_step, tuple(args.cameras))
    log.info(
        "%d poses from %d camera sequences (%d skipped)", len(test.gt), test.sequences, len(test.skipped)
    )
    scores = score(lift, test.points, test.visible, test, args.batch_size, f"lift {args.inputs}")
    result: dict[str, Any] = {
        "dataset": f"Human3.6M {DATASET_LABEL}" + _restriction(args),
        "model": Path(args.model).name,
        "model_id": meta.get("model_id", ""),
        "inputs": "gt" if args.inputs == "gt" else f"detections {Path(args.inputs).name}",
        "subjects": list(args.subjects),
        "actions": list(test.actions),
        "cameras": list(args.cameras),
        "frame_step": args.frame_step,
        "seed": args.seed,
        "sequences": test.sequences,
        "skipped_sequences": list(test.skipped),
        "notes": list(test.notes),
        "misaligned_sequences": list(data.MISALIGNED),
        "paper": PAPER,
        "paper_noise_scale": PAPER_NOISE_SCALE,
        **summarize_scores(scores, test),
        "bone_lengths": bone_length_figures(scores, test),
        "off_axis": off_axis_floor(test),
    }
    if scores.plausibility is not None:
        result["plausibility_deciles"] = plausibility_deciles(scores)
        result["plausibility_spearman"] = plausibility_spearman(scores)
    if args.table_frame_step > 0:
        step = max(args.table_frame_step, args.frame_step)  # never denser than the main figures
        table_set = build_test_set(poses, cameras, None, step, tuple(args.cameras))
        result["tables"] = {
            "inputs": "gt",
            "frame_step": step,
            "poses": len(table_set.gt),
            **robustness_tables(lift, table_set, args.batch_size, args.seed),
        }
    result["wall_time_s"] = round(time.perf_counter() - started, 1)
    return result


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The evaluation's command line, checked (parser.error on a bad value)."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--model", type=Path, required=True, help="ONNX with the repnet contract")
    parser.add_argument("--inputs", default="gt", help="'gt' (projected ground truth) or a detections .npz")
    parser.add_argument("--data-dir", default=None, help=f"Human3.6M folder (default: ${data.DATA_ENV})")
    parser.add_argument("--out-dir", type=Path, default=Path("runs/eval"))
    parser.add_argument("--frame-step", type=int, default=1, help="evaluate every n-th test frame")
    parser.add_argument("--table-frame-step", type=int, default=5, help="noise/occlusion tables; 0: none")
    parser.add_argument("--threads", type=int, default=0, help="onnxruntime threads; 0: its default")
    parser.add_argument("--batch-size", type=int, default=4096)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--subjects", nargs="+", default=list(data.TEST_SUBJECTS))
    parser.add_argument("--actions", nargs="*", default=[], help="only these actions (default: all)")
    parser.add_argument("--cameras", nargs="+", default=list(data.CAMERAS))
    args = parser.parse_args(argv)
    for flag in ("frame_step", "batch_size"):
        if getattr(args, flag) < 1:
            parser.error(f"--{flag.replace('_', '-')} must be >= 1, got {getattr(args, flag)}")
    if args.inputs != "gt" and not Path(args.inputs).is_file():
        parser.error(f"--inputs must be 'gt' or a detections .npz file, got {args.inputs!r} (no such file)")
    if args.table_frame_step < 0:
        parser.error(f"--table-frame-step must be >= 0, got {args.table_frame_step}")
    return args


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """python -m repnet.train.evaluate: evaluate a model and write its report; returns the results."""
    args = parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    result = evaluate(args)
    print(report.write_report(result, args.out_dir))
    log.info("wrote evaluation.json, evaluation.md, per_action.png to %s", args.out_dir)
    return result


if __name__ == "__main__":
    main()
