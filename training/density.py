"""How typical a 3D pose is among real people's: a density over its bone directions and proportions.

The plausibility output ranks the answers by this density (model.Plausibility): a pose far from
every pose people hold (a limb too long, arms crossed through the chest, an elbow bent backwards)
has a low density, and such answers are the wrong ones more often than typical ones. The WGAN
critic is not a density (it is trained to separate real poses from one generator's answers, and
its scores order poses only near that boundary); it ranked the answers' errors less well at every
validation shift (docs/RESULTS.md, "Plausibility: a pose density").

Two independent parts, both fitted to the training subjects' template-aligned poses:
- the 16 bone directions (unit vectors in the template frame the generator answers in), reduced
  by PCA, under a mixture of Gaussians with full covariances (scikit-learn fits it);
- the proportions, each bone's log length minus the mean log length of the pose's bones, under
  one Gaussian whose spread is the five subjects' widened LENGTH_WIDEN times (the lifter's answers
  and other people differ more).
Both are scale-free and unchanged by where the pelvis is. The module evaluates them in torch, so
it exports to ONNX with the generator.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn

from repnet.core import skeleton

# The proportions' Gaussian: the training subjects' covariance, every direction with a standard
# deviation of at least LENGTH_FLOOR (log length), widened LENGTH_WIDEN times. Chosen on validation
# (docs/RESULTS.md): what ranks the answers' errors is mostly a left bone that differs from the
# right one, which the training skeletons never show; a floor of 1 % instead of 0.1 % loses that.
# Widened 2 to 6 times they rank alike, but at 2 the answers to clean 2D average a plausibility of
# 0.4 and a third of those to 40 px noise score 0; at 4 they average 0.55, as real poses 0.5.
LENGTH_FLOOR = 0.001
LENGTH_WIDEN = 4.0


def pose_features(pose: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(N, J, 3) poses (any unit) -> bone directions (N, 3B) and proportions (N, B): each bone's log
    length minus the mean log length of the pose's bones (log of its length over their geometric mean)."""
    parents, children = zip(*skeleton.BONES, strict=True)
    bones = pose[:, list(children)] - pose[:, list(parents)]  # (N, B, 3)
    lengths = bones.norm(dim=-1).clamp_min(1e-9)  # (N, B)
    directions = (bones / lengths.unsqueeze(-1)).flatten(1)
    log_lengths = torch.log(lengths)
    return directions, log_lengths - log_lengths.mean(dim=1, keepdim=True)


class PoseDensity(nn.Module):
    """log p(pose) = log p(directions) + log p(proportions) (up to the PCA's constant).

    Buffers (each used as it is, so that the ONNX file keeps them under these names and
    checkpoint.from_onnx finds them): feature_mean (3B,), projection (3B, D) the principal
    directions as columns, means (K, D), precision_chol (K, D, D) with precision = P P^T
    (scikit-learn's precisions_cholesky_), log_norms (K,) each component's log weight + log |P|
    - D/2 log(2 pi) + the proportions' constant, length_mean (B,), length_precision (B, B).
    """

    feature_mean: torch.Tensor
    projection: torch.Tensor
    means: torch.Tensor
    precision_chol: torch.Tensor
    log_norms: torch.Tensor
    length_mean: torch.Tensor
    length_precision: torch.Tensor

    def __init__(self, components: int = 64, dims: int = 32) -> None:
        """An unfitted density of this shape (fit, or load_state_dict of a fitted one)."""
        super().__init__()
        bones = skeleton.NUM_BONES
        self.register_buffer("feature_mean", torch.zeros(3 * bones))
        self.register_buffer("projection", torch.zeros(3 * bones, dims))
        self.register_buffer("means", torch.zeros(components, dims))
        self.register_buffer("precision_chol", torch.eye(dims).repeat(components, 1, 1))
        self.register_buffer("log_norms", torch.zeros(components))
        self.register_buffer("length_mean", torch.zeros(bones))
        self.register_buffer("length_precision", torch.eye(bones))

    def forward(self, pose: torch.Tensor) -> torch.Tensor:
        """(N, J, 3) pose -> (N,) log density."""
        directions, proportions = pose_features(pose)
        codes = (directions - self.feature_mean) @ self.projection  # (N, D)
        diff = codes.unsqueeze(1) - self.means  # (N, K, D)
        whitened = torch.einsum("nkd,kde->nke", diff, self.precision_chol)
        by_directions = torch.logsumexp(self.log_norms - 0.5 * whitened.pow(2).sum(dim=-1), dim=1)
        off = proportions - self.length_mean  # (N, B)
        return by_directions - 0.5 * ((off @ self.length_precision) * off).sum(dim=1)

    @classmethod
    def fit(
        cls,
        poses_mm: np.ndarray,
        components: int = 64,
        dims: int = 32,
        seed: int = 0,
        length_floor: float = LENGTH_FLOOR,
        length_widen: float = LENGTH_WIDEN,
    ) -> PoseDensity:
        """Fit to (M, J, 3) template-aligned real poses (mm); scikit-learn fits the mixture."""
        from sklearn.mixture import GaussianMixture  # type: ignore[import-untyped]

        directions, proportions = (
            f.numpy() for f in pose_features(torch.from_numpy(poses_mm.astype(np.float64)))
        )
        mean = directions.mean(axis=0)
        basis = np.linalg.svd(directions - mean, full_matrices=False)[2][:dims]
        mixture = GaussianMixture(
            components, covariance_type="full", random_state=seed, reg_covar=1e-4, max_iter=200
        ).fit((directions - mean) @ basis.T)
        chol = mixture.precisions_cholesky_  # (K, D, D)
        log_det = np.log(np.diagonal(chol, axis1=1, axis2=2)).sum(axis=1)
        # The training skeletons are exactly symmetric (a left bone as long as the right one), so the
        # proportions' covariance is singular; every direction gets at least length_floor's variance.
        bones = proportions.shape[1]
        covariance = (np.cov(proportions.T) + length_floor**2 * np.eye(bones)) * length_widen**2
        length_norm = -0.5 * (np.linalg.slogdet(covariance)[1] + bones * math.log(2 * math.pi))
        norms = np.log(mixture.weights_) + log_det - 0.5 * dims * math.log(2 * math.pi) + length_norm
        density = cls(components, dims)
        for name, value in (
            ("feature_mean", mean),
            ("projection", basis.T),
            ("means", mixture.means_),
            ("precision_chol", chol),
            ("log_norms", norms),
            ("length_mean", proportions.mean(axis=0)),
            ("length_precision", np.linalg.inv(covariance)),
        ):
            getattr(density, name).copy_(torch.from_numpy(np.asarray(value, dtype=np.float32)))
        return density.eval()

    @classmethod
    def of_state(cls, state: dict[str, torch.Tensor]) -> PoseDensity:
        """The density of a state_dict (its shape read from the weights)."""
        components, dims = state["means"].shape
        density = cls(components, dims)
        density.load_state_dict(state)
        return density.eval()
