"""Checkpoint -> ONNX (the service's only input from training), with metadata and a parity check."""

from __future__ import annotations

import argparse
import json
import logging
import sys
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import torch

from repnet.core import skeleton
from repnet.train import checkpoint, data, lineage
from repnet.train import plausibility as plausibility_of
from repnet.train.config import RepNetConfig
from repnet.train.density import PoseDensity
from repnet.train.metadata import build_metadata, method_of, training_data
from repnet.train.model import Critic, LiftingGraph, Plausibility, RepNet, load_critic
from repnet.train.plausibility import SCORES, DensityConfig, Score

log = logging.getLogger(__name__)

OPSET = 17
IR_VERSION = 8  # loadable by every onnxruntime >= 1.14


def load_generator(path: Path) -> tuple[RepNet, dict[str, Any]]:
    """Rebuild the generator from a checkpoint written by repnet.train.train, or from an exported
    model (repnet.train.checkpoint.from_onnx); no flags needed."""
    state = checkpoint.load(path)
    return generator_of(state), state


def generator_of(state: dict[str, Any]) -> RepNet:
    """The generator of a loaded checkpoint or exported model's state (checkpoint.load), in eval mode."""
    generator = RepNet(RepNetConfig(**state["model_config"]))
    generator.load_state_dict(state["generator"])
    return generator.eval()


def parity_inputs(poses: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """The (poses, J, 2) pixels and (poses, J) visibility an export checks torch against
    onnxruntime on: people-sized random points around (500, 500), a tenth of the joints hidden."""
    rng = np.random.default_rng(0)
    points = (rng.normal(size=(poses, skeleton.NUM_JOINTS, 2)) * 120 + 500).astype(np.float32)
    visible = (rng.random((poses, skeleton.NUM_JOINTS)) > 0.1).astype(np.float32)
    return points, visible


def export_onnx(
    generator: RepNet,
    path: Path,
    metadata: dict[str, str],
    plausibility: Plausibility | None = None,
    mirror_average: bool = False,
    critic: Critic | None = None,
) -> None:
    """Write the LiftingGraph of `generator` to `path` with the ONNX contract of the service.

    Inputs keypoints_2d (N, 17, 2) px and visibility (N, 17); outputs pose_3d (N, 17, 3) mm
    and camera (N, 2, 3), plausibility (N,) in [0, 1] when a calibrated score is given, and the
    critic's raw score (N,) when a critic is given (LiftingGraph).
    N is dynamic. mirror_average: the graph averages each answer with that of the mirrored
    input (LiftingGraph), one generator run on 2N rows.
    """
    graph = LiftingGraph(generator.eval(), plausibility, mirror_average, critic).eval()
    j = generator.config.num_joints
    example = (torch.randn(2, j, 2) * 100 + 500, torch.ones(2, j))
    outputs = ["pose_3d", "camera"] + (["plausibility"] if plausibility is not None else [])
    outputs += ["critic"] if critic is not None else []
    inputs = ["keypoints_2d", "visibility"]
    axes = {name: {0: "N"} for name in [*inputs, *outputs]}
    doc = "RepNet 2D-to-3D human pose lifting (Wandt & Rosenhahn, CVPR 2019)"
    write_onnx(graph, example, path, (inputs, outputs, axes), doc, metadata)


def write_onnx(
    graph: torch.nn.Module,
    example: tuple[torch.Tensor, ...],
    path: Path,
    names: tuple[list[str], list[str], dict[str, dict[int, str]]],
    doc: str,
    metadata: dict[str, str],
) -> None:
    """Export `graph` at `path` as the service reads models: opset OPSET, IR <= IR_VERSION, the
    given input and output names and dynamic axes, a doc string and custom metadata, checked."""
    import onnx

    inputs, outputs, axes = names
    path.parent.mkdir(parents=True, exist_ok=True)
    with torch.no_grad(), warnings.catch_warnings():
        # The TorchScript exporter is deprecated but gives a plain, small opset-17 graph.
        warnings.simplefilter("ignore", DeprecationWarning)
        torch.onnx.export(
            graph,
            example,
            str(path),
            input_names=inputs,
            output_names=outputs,
            dynamic_axes=axes,
            opset_version=OPSET,
            dynamo=False,
        )
    model = onnx.load(str(path))
    model.ir_version = min(model.ir_version, IR_VERSION)
    model.producer_name = "repnet"
    model.doc_string = doc
    checkpoint.set_metadata(model, metadata)
    onnx.checker.check_model(model)
    onnx.save(model, str(path))


def check_parity(
    generator: RepNet, path: Path, points: np.ndarray, visible: np.ndarray, mirror_average: bool = False
) -> float:
    """Max abs difference (mm) of pose_3d between torch and onnxruntime on (N, 17, 2) points."""
    import onnxruntime as ort

    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    pose_ort = session.run(["pose_3d"], {"keypoints_2d": points, "visibility": visible})[0]
    with torch.no_grad():
        graph = LiftingGraph(generator, mirror_average=mirror_average)
        pose_torch = graph(torch.from_numpy(points), torch.from_numpy(visible))[0]
    return float(np.abs(pose_ort - pose_torch.numpy()).max())


def calibrated_plausibility(
    critic: Critic,
    density: DensityConfig | None,
    data_path: Path,
    val_fraction: float,
    exclude_actions: str = "",
) -> tuple[Plausibility, Critic | None, dict[str, str]]:
    """The plausibility output, calibrated on the real validation poses: the pose density fitted
    to the training poses (density's settings) or, with density None, the critic's score; neither
    sees the poses of exclude_actions (data.without_actions). Returns it, the critic to carry as the
    "critic" output (None when it is the score itself) and the metadata entries."""
    step = density.frame_step if density else 1
    pool, val_sets = data.build_training_sets(data_path, "gt", step, val_fraction, exclude_actions)
    real = data.align_to_template(val_sets["gt"].poses_camera)
    if density is None:
        scorer, table, bones = plausibility_of.build(critic, real)
        entries = plausibility_of.metadata("critic", table, bones)
        log.info("plausibility: the critic, calibrated on %d real validation poses", len(real))
        return scorer, None, entries
    fitted = PoseDensity.fit(pool.poses_aligned, density.components, density.dims, density.seed)
    scorer, table, bones = plausibility_of.build(fitted, real)
    log.info(
        "plausibility: a pose density fitted to %d training poses, calibrated on %d real validation poses",
        len(pool.poses_aligned),
        len(real),
    )
    return scorer, critic, plausibility_of.metadata("density", table, bones)


class NoCritic(ValueError):
    """The checkpoint named for the plausibility critic holds none."""


def run_root(checkpoint_path: Path) -> Path:
    """The folder a lineage's paths are relative to: the one holding the checkpoint's run folder
    (a preset's out-dir for a stage's checkpoint)."""
    return checkpoint_path.resolve().parent.parent


def export_model(
    checkpoint_path: Path,
    output: Path,
    *,
    model_id: str = "",
    critic_checkpoint: Path | None = None,
    plausibility: bool = True,
    score: Score = "density",
    density: DensityConfig | None = None,
    mirror_average: bool = False,
    evaluation: dict[str, Any] | None = None,
    data_dir: str | None = None,
    command: str = "",
    root: Path | None = None,
) -> float:
    """Export a checkpoint's generator (or an exported model's) to `output` with its metadata and
    lineage; with plausibility, a calibrated plausibility output (calibrated_plausibility: score
    "density", a pose density fitted by `density`'s settings, default DensityConfig(), or "critic")
    and the critic of critic_checkpoint (default: the checkpoint's own) as the "critic" output. The
    density and its calibration leave out the actions the generator's run left out (its
    exclude_actions). Returns torch vs onnxruntime's max |diff| (mm).

    command -- the export's command line, recorded path free (lineage); root -- the folder the
    lineage's paths are relative to (default run_root(checkpoint_path)).
    """
    root = root or run_root(checkpoint_path)
    generator, state = load_generator(checkpoint_path)
    train = state.get("train_config", {})
    excluded = train.get("exclude_actions", "")
    critic_path = critic_checkpoint or checkpoint_path
    critic_state = state if critic_checkpoint is None else checkpoint.load(critic_checkpoint)
    scorer, critic, entries, hashes = None, None, None, {}
    if plausibility:
        if not critic_state["critic"]:
            raise NoCritic(
                f"--critic-checkpoint {critic_path}: holds no critic (exported without plausibility)"
            )
        data_path = data.resolve_data_dir(data_dir)
        hashes = lineage.data_hashes(data_path, data.training_files("gt"))
        fit = (density or DensityConfig()) if score == "density" else None
        scorer, critic, entries = calibrated_plausibility(
            load_critic(critic_state), fit, data_path, train.get("val_fraction", 0.1), excluded
        )
    train_command = state.get("command", "")
    if plausibility and critic_checkpoint is not None:
        critic_command = critic_state.get("critic_command", critic_state.get("command", ""))
        train_command = checkpoint.join_commands(train_command, critic_command)
    sources = (checkpoint_path, state), ((critic_path, critic_state) if plausibility else None)
    metadata = build_metadata(
        generator.config,
        model_id=model_id or output.stem,
        train_command=lineage.path_free(train_command, root),
        training_data=training_data(train.get("inputs", "?"), excluded),
        training_method=method_of(train),
        evaluation=evaluation,
        plausibility=entries,
        mirror_average=mirror_average,
        lineage=lineage.export_lineage(lineage.path_free(command, root), *sources, hashes, root),
    )
    export_onnx(generator, output, metadata, scorer, mirror_average, critic)
    diff = check_parity(generator, output, *parity_inputs(), mirror_average)
    log.info(
        "wrote %s (%.1f MB); torch vs onnxruntime max |diff| = %.2e mm",
        output,
        output.stat().st_size / 1e6,
        diff,
    )
    return diff


def main(argv: list[str] | None = None) -> None:
    """python -m repnet.train.export: a checkpoint (or an exported model) to an ONNX model."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--checkpoint", type=Path, required=True)
    parser.add_argument("--output", type=Path, required=True)
    parser.add_argument("--model-id", default="")
    parser.add_argument("--evaluation", type=Path, help="JSON of evaluation figures to embed")
    parser.add_argument(
        "--plausibility",
        type=lambda v: v.lower() in ("1", "true", "yes"),
        default=True,
        help="add the calibrated plausibility output and the critic (needs the Human3.6M data; default true)",
    )
    parser.add_argument(
        "--plausibility-score",
        choices=SCORES,
        default="density",
        help="what plausibility ranks by: a pose density fitted to the training poses (default) or the "
        "critic's score (models before repnet-h36m-v7)",
    )
    parser.add_argument(
        "--critic-checkpoint",
        type=Path,
        help="take the critic from this checkpoint (default: --checkpoint's); e.g. a critic trained "
        "against corrupted real poses, which does not depend on the generator, or an exported .onnx "
        "with a critic",
    )
    parser.add_argument(
        "--mirror-average",
        type=lambda v: v.lower() in ("1", "true", "yes"),
        default=False,
        help="average every answer with the mirrored answer to the mirrored input (test-time flip "
        "augmentation; twice the generator's work; default false)",
    )
    parser.add_argument(
        "--data-dir", default=None, help="Human3.6M folder (default: $REPNET_H36M_DIR, ../shared)"
    )
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    root = run_root(args.checkpoint)
    try:
        export_model(
            args.checkpoint,
            args.output,
            model_id=args.model_id,
            critic_checkpoint=args.critic_checkpoint if args.plausibility else None,
            plausibility=args.plausibility,
            score=args.plausibility_score,
            mirror_average=args.mirror_average,
            evaluation=json.loads(args.evaluation.read_text()) if args.evaluation else None,
            data_dir=args.data_dir,
            command=lineage.command_line(
                argv if argv is not None else sys.argv[1:], root, "repnet.train.export"
            ),
            root=root,
        )
    except NoCritic as err:
        parser.error(str(err))


if __name__ == "__main__":
    main()
