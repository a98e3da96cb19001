"""`repnet adapt INPUT... -o adapted.onnx`: adapt a model to the user's own unlabeled 2D detections.

repnet.cli.main defines the flags (so `repnet adapt --help` works without torch) and calls run() here;
this needs the `train` extra. The steps are repnet.train.adapt's; the report, the refusal of a worse
model and the export are repnet.train.adapt_report's.
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import json
import math
import shlex
import sys
import time
from dataclasses import asdict
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from repnet.core.contract import DEFAULT_FPS
from repnet.core.inputs import MODEL_ID, MODEL_ID_RULE
from repnet.core.links import kept_links
from repnet.runtime.loading import BUNDLED_CAUSAL, BUNDLED_MODEL, serves_under
from repnet.train import checkpoint, lineage
from repnet.train.adapt import Adaptation, AdaptConfig, ConfigMismatch, split_holdout
from repnet.train.adapt_report import (
    MIN_HOLDOUT,
    SHARE_STEP_PCT,
    Figures,
    adapted_figures,
    answers,
    default_steps,
    export_adapted,
    measure,
    parent_scorer,
    render,
    report_record,
    worse,
)
from repnet.train.export import generator_of
from repnet.train.model import Critic
from repnet.train.prior import PosePrior

PROBE_POSES = 256  # held-out poses the progress bar's figures are measured on
PROBE_EVERY = 50  # steps between two such measurements


def say(message: str) -> None:
    """A line on stderr."""
    print(f"repnet adapt: {message}", file=sys.stderr, flush=True)


def input_hashes(specs: list[str]) -> list[dict[str, str]]:
    """sha256 of each input: of the file, or of a folder's (or glob's) files by name and content."""
    out = []
    for spec in specs:
        path = Path(spec)
        if path.is_file():
            out.append({"input": path.name, "sha256": lineage.file_sha256(path)})
            continue
        files = sorted(path.iterdir()) if path.is_dir() else sorted(Path().glob(spec))
        h = hashlib.sha256()
        for f in (f for f in files if f.is_file()):
            h.update(f.name.encode() + b"\0" + lineage.file_sha256(f).encode())
        out.append({"input": path.name or spec, "sha256": h.hexdigest(), "files": str(len(files))})
    return out


def run_dir(args: argparse.Namespace, parent_sha: str, inputs_sha: str, prior_sha: str = "") -> Path:
    """Where the run checkpoints: --run-dir, else a folder of the cache named by the output, the
    parent, the inputs and the --prior ("": the shipped one), so --resume finds it again."""
    if args.run_dir is not None:
        return Path(args.run_dir)
    key = hashlib.sha256(f"{args.output.resolve()}|{parent_sha}|{inputs_sha}|{prior_sha}".encode())
    return lineage.cache_dir() / "adapt" / f"{args.output.stem}-{key.hexdigest()[:12]}"


def _usage(args: argparse.Namespace) -> tuple[str | None, tuple[PosePrior | None, str]]:
    """What is wrong with -o or --prior (None: nothing), and the pose prior of --prior read once with
    its file's sha256 ((None, ""): the shipped one)."""
    shipped: tuple[PosePrior | None, str] = (None, "")
    if (problem := _output_problem(args)) is not None:
        return f"-o {args.output}: {problem}", shipped
    if args.prior is None:
        return None, shipped
    try:
        return None, (PosePrior.load(Path(args.prior)), lineage.file_sha256(Path(args.prior)))
    except (OSError, KeyError, ValueError) as err:
        writer = "python -m repnet.train.prior writes one"
        return f"--prior {args.prior}: not a pose prior ({writer}): {err}", shipped


def _given(value: float | None, default: float) -> float:
    return default if value is None else value


def _config(args: argparse.Namespace, steps: int) -> AdaptConfig:
    defaults = AdaptConfig()
    return AdaptConfig(
        steps=steps,
        minutes=_given(args.minutes, defaults.minutes),
        holdout_fraction=args.holdout_fraction,
        prior_poses=args.prior_poses,
        reprojection_weight=_given(args.reprojection_weight, defaults.reprojection_weight),
        smoothness_weight=_given(args.smoothness_weight, defaults.smoothness_weight),
        adversarial_weight=_given(args.adversarial_weight, defaults.adversarial_weight),
        residual_share=0.0 if args.residuals == "off" else defaults.residual_share,
        residual_mode=args.residuals if args.residuals in ("mean", "pose") else defaults.residual_mode,
        seed=args.seed,
    )


def _steps(args: argparse.Namespace, before: Figures, runs: list[int]) -> int:
    """--steps, or the length default_steps chooses from the parent's figures on the held-out 2D and
    their runs (said with its reason)."""
    if args.steps is not None:
        return int(args.steps)
    steps, why = default_steps(before, max(runs))
    say(f"{steps} steps: {why} (--steps sets another length)")
    return steps


def _progress(adaptation: Adaptation, probe: tuple[np.ndarray, np.ndarray], scorer: Any, bar: tqdm) -> Any:
    """The on_step callback: the bar moves every step and shows the held-out probe's reprojection
    error (px) and plausibility every PROBE_EVERY steps."""

    def on_step(step: int, _terms: Any) -> None:
        bar.update(1)
        if step % PROBE_EVERY == 0 and len(probe[0]):
            f = measure(adaptation.trainer.generator, scorer, probe[0], probe[1], adaptation.mirror_average)
            bar.set_postfix(reproj_px=f"{f.reprojection_px:.2f}", plausibility=f"{f.plausibility:.3f}")

    return on_step


def run(
    args: argparse.Namespace,
    points: np.ndarray,
    visible: np.ndarray,
    counts: tuple[int, ...],
    skipped: int,
    previous: np.ndarray | None = None,
) -> int:
    """The command on the inputs' usable poses (`points` (N, 17, 2) px and `visible` (N, 17), `counts`
    per input, `skipped` by the input rules, `previous` (N,) the row of each pose's frame before, -1
    where none: repnet.cli.adapt reads them): adapt, report, refuse or write. 0 written, 1 refused
    (worse), 2 usage."""
    if args.threads:
        torch.set_num_threads(args.threads)
    problem, (prior, prior_sha) = _usage(args)
    if problem is not None:
        say(problem)
        return 2
    held = split_holdout(list(counts), args.holdout_fraction)
    train = (points[~held], visible[~held])
    links = None if previous is None else kept_links(previous, ~held)
    test = (points[held], visible[held]) if held.any() else train
    runs = [int(part.sum()) for part in np.split(held, np.cumsum(counts)[:-1])] if held.any() else None
    say(
        f"{len(points)} poses ({skipped} skipped by the input rules): {len(train[0])} to adapt on, "
        f"{int(held.sum())} held out"
    )
    parent_path = Path(args.model) if args.model else BUNDLED_MODEL
    parent = checkpoint.from_onnx(parent_path)  # one read of the file: weights and metadata
    meta = parent["metadata"]
    scorer = parent_scorer(parent, meta)
    mirror = bool(json.loads(meta.get("mirror_average", "false")))
    before, was = answers(generator_of(parent), scorer, *test, mirror, runs)
    config = _config(args, _steps(args, before, runs or [len(test[0])]))
    parent_sha = lineage.file_sha256(parent_path)
    adaptation = Adaptation(
        config, parent, *train, prior=prior, mirror_average=mirror, threads=args.threads, previous=links
    )
    state = run_dir(args, parent_sha, adaptation.inputs_sha, prior_sha) / "adapt.pt"
    if args.resume and state.is_file():
        try:
            adaptation.load(state)
        except (ConfigMismatch, checkpoint.UnsafeCheckpoint) as err:
            say(f"error: {err}")
            return 2
        say(f"resumed {state} at step {adaptation.step} of {config.steps}")
    elif args.resume:
        say(f"nothing to resume in {state.parent}: starting afresh")
    done = _adapt(adaptation, state, (test[0][:PROBE_POSES], test[1][:PROBE_POSES]), scorer)
    if done is None:
        return 130
    # Samples/s over the whole run (every call of a resumed one): what its wall time bought.
    rate = adaptation.step * config.batch_size / max(adaptation.elapsed, 1e-9)
    say(
        f"{adaptation.step} of {config.steps} steps in {adaptation.elapsed / 60:.1f} min "
        f"({rate:.0f} samples/s){'' if done else f'; {kept(state)}: run again with --resume to go on'}"
    )
    after = adapted_figures(was, adaptation.trainer.generator, scorer, test, mirror, runs)
    print(render(before, after, len(test[0])))
    reasons = worse(before, after)
    if reasons and not args.force:
        also = f"; also {'; '.join(reasons[1:])}" if reasons[1:] else ""
        say(
            f"not written: the adapted model is worse on the held-out poses; decided by: {reasons[0]}{also}. "
            f"--force writes it anyway ({kept(state)}: --resume --force writes it without adapting again)"
        )
        if (advice := more_data(len(test[0]), args.holdout_fraction)) is not None:
            say(advice)
        return 1
    record = {
        "model_id": args.model_id or args.output.stem,
        "parent": {"model_id": meta.get("model_id", parent_path.stem), "sha256": parent_sha},
        "prior": {"sha256": prior_sha} if prior_sha else None,
        "command": lineage.path_free(shlex.join(args.command_line), Path.cwd()),
        "inputs": input_hashes(list(args.input)),
        "poses": int(len(train[0])),
        "holdout_poses": int(held.sum()),
        "steps": adaptation.step,
        "wall_time_s": round(adaptation.elapsed, 1),
        "samples_per_s": round(rate, 1),
        "config": asdict(config),
        "report": report_record(before, after, len(test[0])),
        "refused_but_forced": reasons,
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "parent_lineage": json.loads(meta["lineage"]) if "lineage" in meta else None,
    }
    start = time.monotonic()
    # The adapted critic goes on as the file's "critic" output, unless the plausibility is the critic.
    critic = None if isinstance(scorer.score, Critic) else adaptation.trainer.critic.eval()
    diff = export_adapted(adaptation.trainer.generator, scorer, meta, args.output, record, mirror, critic)
    took = time.monotonic() - start
    check = f"torch vs onnxruntime {diff:.1e} mm, {took:.1f} s"
    written(args.output, record["model_id"], reasons, check, keeps_temporal(parent_sha, meta))
    settle_checkpoint(state, deleted=done and args.run_dir is None)  # a --run-dir is the user's
    return 0


def settle_checkpoint(state: Path, deleted: bool) -> None:
    """Delete the cache's checkpoint of a finished, written run (and its folder when empty), or say
    where it is kept."""
    if not deleted:
        say(kept(state))
        return
    state.unlink(missing_ok=True)
    with contextlib.suppress(OSError):
        state.parent.rmdir()  # when empty
    say(f"its checkpoint {state} is deleted: the model holds what it learned")


def keeps_temporal(parent_sha: str, meta: dict[str, str]) -> bool:
    """Whether the bundled temporal models run over a model adapted from the parent of file hash
    `parent_sha` and metadata `meta` (repnet.runtime.loading.serves_under: the model adapted from
    serves under them as well as its parent)."""
    if not BUNDLED_CAUSAL.is_file():
        return False
    base = checkpoint.read_metadata(BUNDLED_CAUSAL).get("base_model_sha256", "")
    return serves_under(base, parent_sha, meta)


def written(output: Path, model: str, reasons: list[str], check: str, temporal: bool) -> None:
    """Say what was decided and why, where the model is, and whether temporal lifting runs over it."""
    why = (
        f"written because of --force, though {'; '.join(reasons)}"
        if reasons
        else "written: no figure got worse beyond its limit (docs/TRAINING.md, Report)"
    )
    over = (
        "the temporal models of its parent run over it (GET /v1/models lists them)"
        if temporal
        else "the bundled temporal models were trained on another single-frame model and do not run over "
        "it (python -m repnet.train.temporal_train --base-model trains them over it)"
    )
    serve = "serve it with --model-path or from REPNET_MODEL_DIR"
    say(f"{why}. Wrote {output} (model {model}, {check}): {serve}; {over}")


def _output_problem(args: argparse.Namespace) -> str | None:
    """What is wrong with -o, if anything."""
    if args.output.suffix != ".onnx":
        return "the adapted model is an .onnx file"
    if not args.output.parent.is_dir():
        return f"the folder {args.output.parent} does not exist"
    if args.model_id is None and MODEL_ID.fullmatch(args.output.stem) is None:
        return f"its name is the model id, which must be {MODEL_ID_RULE}; give --model-id"
    return None


def _adapt(
    adaptation: Adaptation, state: Path, probe: tuple[np.ndarray, np.ndarray], scorer: Any
) -> bool | None:
    """Adaptation.run with its progress bar: True when all steps are done, False at the time limit,
    None when interrupted (Ctrl-C), said with the checkpoint a rerun resumes from."""
    steps = adaptation.config.steps
    try:
        with tqdm(total=steps, initial=adaptation.step, desc="adapt", unit="step", file=sys.stderr) as bar:
            on_step = _progress(adaptation, probe, scorer, bar)
            return adaptation.run(adaptation.config.minutes, state, on_step=on_step)
    except KeyboardInterrupt:
        # No save here: an interrupted step may have half-updated the weights; the last periodic save stands.
        said = (
            f"{kept(state)}: --resume goes on from it" if state.is_file() else "no checkpoint was written yet"
        )
        say(f"interrupted; {said}")
        return None


def kept(state: Path) -> str:
    """Where the run's checkpoint is kept, and its size."""
    size = state.stat().st_size if state.is_file() else 0
    return f"its checkpoint is kept in {state} ({size / 1e6:.1f} MB)"


def more_data(holdout: int, fraction: float) -> str | None:
    """What a refused run on too few held-out poses lacks (MIN_HOLDOUT, of the refusal's tolerance),
    and about how many poses to give; None when the held-out part is large enough."""
    if holdout >= MIN_HOLDOUT:
        return None
    poses = math.ceil(MIN_HOLDOUT / fraction) if fraction > 0 else MIN_HOLDOUT
    return (
        f"only {holdout} held-out poses: the decision needs at least {MIN_HOLDOUT} (one answer turning "
        f"one way or the other moves a share by {100 / max(holdout, 1):.0f} points, not at most "
        f"{SHARE_STEP_PCT:g}); give about {poses} poses ({poses} frames of "
        f"one person, {poses / DEFAULT_FPS:.0f} s at {DEFAULT_FPS:g} fps) or more"
    )
