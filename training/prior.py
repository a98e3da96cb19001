"""A compact 3D pose prior that may ship where Human3.6M may not: a Gaussian mixture over the
directions of the skeleton's bones, and the bones' lengths.

`repnet adapt` needs 3D poses that are never paired with the user's 2D (the paper's unpaired
pool). The Human3.6M poses themselves are research-only and may not be redistributed, so what
ships is a statistical model fitted to the training subjects' poses, under the same terms as the
model weights fitted to them: poses are drawn from it, never looked up.

A pose is its 16 bone directions (unit vectors, Z up, turned about Z so that its hips face +Y)
and its bone lengths. The directions are reduced by PCA and modelled by a Gaussian mixture
(scikit-learn fits it; sampling needs numpy only); lengths are the mean length of each bone,
scaled per person by a log-normal factor, with a small per-bone factor on top. Forward kinematics
turns a draw into a (J, 3) pose in mm, pelvis at the origin.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from repnet.core import skeleton

PRIOR_FILE = Path(__file__).parent / "assets" / "pose_prior_h36m.npz"
LICENCE = (
    "A statistical model fitted to Human3.6M poses (Ionescu et al., TPAMI 2014): like the model "
    "weights, academic, non-commercial research use only, under the Human3.6M licence."
)


def _side_free_bones() -> list[int]:
    """For each bone, the index of the bone it shares a length factor with: the left one of a
    left/right pair, itself otherwise."""
    names = skeleton.JOINT_NAMES
    mirrored = [names.index(n.replace("right_", "left_")) for n in names]
    bones = list(skeleton.BONES)
    return [bones.index((mirrored[p], mirrored[c])) for p, c in bones]


_SIDE_FREE = _side_free_bones()


def _bone_vectors(poses: np.ndarray) -> np.ndarray:
    """(N, J, 3) -> (N, B, 3) child minus parent."""
    parents, children = zip(*skeleton.BONES, strict=True)
    return poses[:, list(children)] - poses[:, list(parents)]


def face_forward(poses: np.ndarray) -> np.ndarray:
    """(N, J, 3) world poses (Z up) turned about Z so that left hip minus right hip points along
    +X (the person faces +Y or -Y alike for every pose), pelvis at the origin."""
    centred = poses - poses[:, skeleton.ROOT : skeleton.ROOT + 1]
    across = centred[:, skeleton.LEFT_HIP, :2] - centred[:, skeleton.RIGHT_HIP, :2]
    angle = np.arctan2(across[:, 1], across[:, 0])
    c, s = np.cos(-angle), np.sin(-angle)
    turned = centred.copy()
    turned[..., 0] = c[:, None] * centred[..., 0] - s[:, None] * centred[..., 1]
    turned[..., 1] = s[:, None] * centred[..., 0] + c[:, None] * centred[..., 1]
    return turned


@dataclass(frozen=True)
class PosePrior:
    """The fitted prior: PCA of the bone directions, a mixture in its space, and the lengths."""

    mean_lengths: np.ndarray  # (B,) mm
    person_scale_std: float  # std of log(person scale)
    bone_scale_std: np.ndarray  # (B,) std of log(bone length / (mean * person scale))
    pca_mean: np.ndarray  # (3B,)
    pca_basis: np.ndarray  # (D, 3B) rows: principal directions
    weights: np.ndarray  # (K,)
    means: np.ndarray  # (K, D)
    chol: np.ndarray  # (K, D, D) lower Cholesky factors of the covariances

    def sample(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """(n, J, 3) float32 poses in mm, Z up, facing +-Y, pelvis at the origin."""
        component = rng.choice(len(self.weights), size=n, p=self.weights / self.weights.sum())
        z = rng.standard_normal((n, self.means.shape[1]))
        codes = self.means[component] + np.einsum("nij,nj->ni", self.chol[component], z)
        directions = (codes @ self.pca_basis + self.pca_mean).reshape(n, -1, 3)
        directions /= np.maximum(np.linalg.norm(directions, axis=-1, keepdims=True), 1e-9)
        person = np.exp(rng.standard_normal(n) * self.person_scale_std)
        # One factor per left/right pair: a person's left arm is as long as the right one.
        per_bone = np.exp(
            rng.standard_normal((n, len(self.mean_lengths)))[:, _SIDE_FREE] * self.bone_scale_std
        )
        lengths = self.mean_lengths * person[:, None] * per_bone  # (n, B)
        poses = np.zeros((n, skeleton.NUM_JOINTS, 3))
        for b, (parent, child) in enumerate(skeleton.BONES):  # parents come before their children
            poses[:, child] = poses[:, parent] + directions[:, b] * lengths[:, b, None]
        return poses.astype(np.float32)

    def save(self, path: Path) -> None:
        """Write the prior as an .npz of its arrays."""
        path.parent.mkdir(parents=True, exist_ok=True)
        arrays = {name: np.asarray(getattr(self, name)) for name in self.__dataclass_fields__}
        floats = {k: v.astype(np.float32) for k, v in arrays.items()}
        np.savez_compressed(path, licence=np.array(LICENCE), **floats)  # type: ignore[arg-type]

    @classmethod
    def load(cls, path: Path = PRIOR_FILE) -> PosePrior:
        """Read what save wrote."""
        with np.load(path) as arrays:
            values = {k: arrays[k].astype(np.float64) for k in cls.__dataclass_fields__}
        values["person_scale_std"] = float(values["person_scale_std"])
        return cls(**values)


def fit(poses_world: np.ndarray, components: int = 48, dims: int = 32, seed: int = 0) -> PosePrior:
    """Fit the prior to (N, J, 3) world poses in mm (Z up); scikit-learn fits the mixture."""
    from sklearn.mixture import GaussianMixture  # type: ignore[import-untyped]

    turned = face_forward(poses_world.astype(np.float64))
    bones = _bone_vectors(turned)  # (N, B, 3)
    lengths = np.linalg.norm(bones, axis=-1)  # (N, B)
    directions = (bones / np.maximum(lengths[..., None], 1e-9)).reshape(len(bones), -1)
    mean_lengths = lengths.mean(axis=0)
    log_ratio = np.log(lengths / mean_lengths)
    person = log_ratio.mean(axis=1)
    pca_mean = directions.mean(axis=0)
    _, _, vt = np.linalg.svd(directions - pca_mean, full_matrices=False)
    basis = vt[:dims]
    codes = (directions - pca_mean) @ basis.T
    mixture = GaussianMixture(components, covariance_type="full", random_state=seed, reg_covar=1e-5)
    mixture.fit(codes)
    return PosePrior(
        mean_lengths=mean_lengths,
        person_scale_std=float(person.std()),
        bone_scale_std=(log_ratio - person[:, None]).std(axis=0),
        pca_mean=pca_mean,
        pca_basis=basis,
        weights=mixture.weights_ / mixture.weights_.sum(),
        means=mixture.means_,
        chol=np.linalg.cholesky(mixture.covariances_),
    )


def main(argv: list[str] | None = None) -> None:
    """python -m repnet.train.prior: fit the prior to the training subjects' poses (validation tails
    left out) and write it; reproduces the shipped file."""
    import argparse

    from repnet.train import data

    parser = argparse.ArgumentParser(description=main.__doc__)
    parser.add_argument(
        "--data-dir", help="Human3.6M folder (default: $REPNET_H36M_DIR or ../shared/data/h36m)"
    )
    parser.add_argument("--frame-step", type=int, default=5, help="every n-th training frame (default 5)")
    parser.add_argument("--components", type=int, default=48, help="mixture components (default 48)")
    parser.add_argument("--dims", type=int, default=32, help="PCA dimensions of the directions (default 32)")
    parser.add_argument(
        "--out", type=Path, default=PRIOR_FILE, help=f"output .npz (default {PRIOR_FILE.name})"
    )
    parser.add_argument(
        "--exclude-actions",
        default="",
        help="Human3.6M actions left out, comma-separated (e.g. Sitting,SittingDown; default none)",
    )
    args = parser.parse_args(argv)
    data_dir = data.resolve_data_dir(args.data_dir)
    pool, _ = data.build_training_sets(data_dir, "gt", args.frame_step, exclude_actions=args.exclude_actions)
    assert pool.poses_world is not None
    fitted = fit(pool.poses_world, components=args.components, dims=args.dims)
    fitted.save(args.out)
    print(f"fitted to {len(pool.poses_world)} poses -> {args.out}")


if __name__ == "__main__":
    main()
