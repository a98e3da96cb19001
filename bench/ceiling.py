"""The service with the model taken out: what HTTP and gRPC cost on their own (the transport ceiling).

    python -m bench.ceiling [service flags]   (the same flags as `python -m repnet serve`)

Everything a request goes through runs as in the service (validation, format conversion, the
batcher, the reply with its camera geometry, metrics) except onnxruntime: the lifter answers each
batch with copies of one real prediction. It runs the service's workers (--workers, default one per
usable CPU) under the same supervisor. bench.run measures it next to the service, so the report
shows how close to the roof the Python transports could get at all on the machine.
"""

from __future__ import annotations

import sys
from dataclasses import fields
from pathlib import Path

import numpy as np

if __package__ in (None, ""):  # `python bench/ceiling.py`
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench.stats import sample_poses
from repnet.runtime.lifter import Lifter, Prediction
from repnet.server.app import load_lifter
from repnet.server.app import main as serve_main
from repnet.server.config import Settings


class ConstantLifter(Lifter):
    """Answers every batch with one real prediction repeated: no model run."""

    def __init__(self, lifter: Lifter) -> None:
        super().__init__(lifter.session, lifter.path)
        pose = sample_poses(1)
        self.answer = lifter.lift(pose, np.ones(pose.shape[:2], bool))

    def lift(self, keypoints_2d: np.ndarray, visibility: np.ndarray) -> Prediction:
        """The stored prediction, once per pose."""
        n = keypoints_2d.shape[0]
        values = {f.name: getattr(self.answer, f.name) for f in fields(Prediction)}
        return Prediction(**{k: None if v is None else np.repeat(v, n, axis=0) for k, v in values.items()})


def constant_lifter(settings: Settings) -> Lifter:
    """The service's model, answering with one stored prediction."""
    return ConstantLifter(load_lifter(settings))


def main(argv: list[str] | None = None) -> int:
    """Serve like `python -m repnet serve`, with the model taken out: as many workers (each a
    `python -m bench.ceiling`) under the same supervisor, so that it compares with the service."""
    return serve_main(
        sys.argv[1:] if argv is None else argv, module=("bench.ceiling",), lifter=constant_lifter
    )


if __name__ == "__main__":
    sys.exit(main())
