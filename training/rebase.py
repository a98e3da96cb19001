"""Carry temporal models over to a new single-frame model whose generator is unchanged.

A temporal model (repnet.train.temporal_train) refines the answers of one single-frame model and names it
by its file's sha256 (metadata base_model_sha256), which the service checks at start. A new export that
changes only the critic (the plausibility output) gives the same pose_3d and camera to the bit but a
new file, so the temporal models would be left out. This checks that the two single-frame models
hold the same generator weights and answer the same inputs identically, then rewrites the temporal
models' base_model_sha256 and base_model_id and records the move in their lineage:

python -m repnet.train.rebase --old v6.onnx --new service/models/repnet-h36m.onnx \
    service/models/repnet-h36m-temporal-causal.onnx service/models/repnet-h36m-temporal-offline.onnx
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import numpy as np
import onnxruntime as ort
import torch

from repnet.core import skeleton
from repnet.train import checkpoint, lineage

log = logging.getLogger(__name__)

CHECK_POSES = 4096


class NotTheSameGenerator(ValueError):
    """The two single-frame models do not give the same answers."""


def _answers(path: Path, points: np.ndarray, visible: np.ndarray) -> list[np.ndarray]:
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    return list(session.run(["pose_3d", "camera"], {"keypoints_2d": points, "visibility": visible}))


def check_same_generator(old: Path, new: Path, poses: int = CHECK_POSES) -> None:
    """Raise NotTheSameGenerator unless old and new hold the same generator weights and give
    bit-identical pose_3d and camera on `poses` random inputs (some joints hidden)."""
    weights_old, weights_new = checkpoint.load(old)["generator"], checkpoint.load(new)["generator"]
    if weights_old.keys() != weights_new.keys() or not all(
        torch.equal(weights_old[name], weights_new[name]) for name in weights_old
    ):
        raise NotTheSameGenerator(f"{new}: its generator weights are not those of {old}")
    rng = np.random.default_rng(0)
    points = (rng.normal(size=(poses, skeleton.NUM_JOINTS, 2)) * 120 + 500).astype(np.float32)
    visible = (rng.random((poses, skeleton.NUM_JOINTS)) > 0.1).astype(np.float32)
    answers = zip(
        ("pose_3d", "camera"), _answers(old, points, visible), _answers(new, points, visible), strict=True
    )
    for name, a, b in answers:
        if not np.array_equal(a, b):
            raise NotTheSameGenerator(
                f"{new}: its {name} differs from {old}'s (max |diff| {np.abs(a - b).max():.3g})"
            )


def rebase(temporal: Path, old: Path, new: Path) -> None:
    """Point the temporal model at `temporal` from single-frame model `old` to `new` (checked with
    check_same_generator by the caller): base_model_sha256, base_model_id, and lineage["rebased"]."""
    import onnx

    model = onnx.load(str(temporal))
    meta = checkpoint.metadata_of(model)
    old_sha, new_sha = lineage.file_sha256(old), lineage.file_sha256(new)
    if meta.get("base_model_sha256") != old_sha:
        raise ValueError(
            f"{temporal}: trained over the model with sha256 {meta.get('base_model_sha256', '?')[:12]}, "
            f"not {old.name} ({old_sha[:12]})"
        )
    new_id = checkpoint.read_metadata(new).get("model_id", new.stem)
    record = json.loads(meta.get("lineage", "{}"))
    record.setdefault("rebased", []).append(
        {
            "from": {"model_id": meta.get("base_model_id", ""), "sha256": old_sha},
            "to": {"model_id": new_id, "sha256": new_sha},
            "check": f"same generator weights; pose_3d and camera bit-identical on {CHECK_POSES} inputs",
        }
    )
    meta.update(base_model_sha256=new_sha, base_model_id=new_id, lineage=json.dumps(record))
    checkpoint.set_metadata(model, meta)
    onnx.save(model, str(temporal))
    log.info("%s: now over %s (%s, sha256 %s)", temporal, new.name, new_id, new_sha[:12])


def main(argv: list[str] | None = None) -> None:
    """python -m repnet.train.rebase --old OLD.onnx --new NEW.onnx TEMPORAL.onnx..."""
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--old", type=Path, required=True, help="the model they were trained over")
    parser.add_argument("--new", type=Path, required=True, help="the single-frame model to move them to")
    parser.add_argument("temporal", type=Path, nargs="+", help="temporal model files, rewritten in place")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        check_same_generator(args.old, args.new)
    except NotTheSameGenerator as err:
        parser.error(str(err))
    for path in args.temporal:
        rebase(path, args.old, args.new)


if __name__ == "__main__":
    main()
