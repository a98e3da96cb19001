"""The temporal model: a window of one person's frames -> the 3D pose of one of them.

It refines what the single-frame model answered. Its input, per frame, is that model's
pose_3d_camera (mm, root at the origin), the 2D keypoints (normalised as the single-frame model
normalises them) and their visibility, plus how the 2D centroid and size move; frames come at
any rate and are first resampled onto a GRID_FPS grid (linear, sequences.resample), so one model
serves 25-60 fps. Its answer is a smoothing of the window's single-frame poses with a learned
kernel (initialised as a fixed filter: a Gaussian for offline windows, a causal straight-line fit
for causal ones) plus a learned correction: a temporal convolution network in the manner of
VideoPose3D (Pavllo et al., CVPR 2019: dilated 1D convolutions, equal to strided ones on a window
of exactly the receptive field), zero at the start so that training starts from the filter.

causal: the answer for the window's last frame (frames <= t only); offline: for its centre.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from repnet.core import skeleton

GRID_FPS = 50.0
J = skeleton.NUM_JOINTS
POSE_CHANNELS = 3 * J
FEATURES = 3 * J + 2 * J + J + 3  # pose (m), normalised 2D, visibility, centroid velocity, log size ratio


@dataclass(frozen=True)
class TemporalConfig:
    """Shape of the temporal model."""

    mode: str = "offline"  # "causal": answers the window's last frame; "offline": its centre
    widths: tuple[int, ...] = (3, 3, 3, 3)  # kernel of each layer: receptive field their product
    channels: int = 256
    dropout: float = 0.1
    smooth_sigma: float = 4.0  # offline: the initial kernel's Gaussian sigma, grid frames
    causal_fit: int = 15  # causal: the initial kernel fits a line to this many last grid frames

    @property
    def window(self) -> int:
        """T: grid frames in one window (the receptive field)."""
        return math.prod(self.widths)

    @property
    def target(self) -> int:
        """The grid frame of the window that is answered."""
        return self.window - 1 if self.mode == "causal" else (self.window - 1) // 2


@dataclass(frozen=True)
class TemporalTrainConfig:
    """One temporal model's training run."""

    steps: int = 6000
    batch: int = 32  # runs of `outputs` consecutive answers per step
    outputs: int = 64
    lr: float = 1e-3
    final_lr: float = 0.05  # of lr, at the end of the cosine
    weight_decay: float = 1e-4
    velocity_weight: float = 1.0  # of the velocity error (m / frame) beside the position error (m)
    acceleration_weight: float = 1.0
    val_every: int = 1000
    checkpoint_every: int = 250
    seed: int = 0


def initial_kernel(config: TemporalConfig) -> np.ndarray:
    """(T,) the fixed filter the learned smoothing starts from; it sums to 1."""
    t = np.arange(config.window, dtype=np.float64)
    if config.mode == "causal":
        if not 2 <= config.causal_fit <= config.window:
            raise ValueError(f"causal_fit must be 2..{config.window} (the window), got {config.causal_fit}")
        kernel = np.zeros(config.window)
        fit = np.arange(-config.causal_fit + 1, 1, dtype=np.float64)
        kernel[-config.causal_fit :] = np.linalg.pinv(np.vander(fit, 2, increasing=True))[0]
        return kernel
    if config.mode != "offline":
        raise ValueError(f"mode must be causal or offline, got {config.mode!r}")
    kernel = np.exp(-0.5 * ((t - config.target) / config.smooth_sigma) ** 2)
    return kernel / kernel.sum()


def grid_features(poses: torch.Tensor, keypoints: torch.Tensor, visibility: torch.Tensor) -> torch.Tensor:
    """(N, T, J, 3) mm poses, (N, T, J, 2) px keypoints, (N, T, J) visibility on the grid ->
    (N, FEATURES, T) network input."""
    n, t = poses.shape[:2]
    w = visibility.unsqueeze(-1)  # (N, T, J, 1)
    count = visibility.sum(dim=2).clamp_min(1.0)  # (N, T)
    mean = (keypoints * w).sum(dim=2) / count.unsqueeze(-1)  # (N, T, 2)
    centred = (keypoints - mean.unsqueeze(2)) * w
    size = torch.sqrt(centred.pow(2).sum(dim=(2, 3)) / (2 * count)).clamp_min(1e-6)  # (N, T)
    normalised = centred / size[..., None, None]
    velocity = (mean[:, 1:] - mean[:, :-1]) / size[:, 1:, None]  # (N, T-1, 2)
    growth = torch.log(size[:, 1:] / size[:, :-1]).unsqueeze(-1)  # (N, T-1, 1)
    motion = torch.cat([velocity, growth], dim=-1)
    motion = torch.cat([torch.zeros_like(motion[:, :1]), motion], dim=1)  # (N, T, 3)
    parts = [poses.reshape(n, t, -1) / 1000.0, normalised.reshape(n, t, -1), visibility, motion]
    return torch.cat(parts, dim=-1).transpose(1, 2)


class TemporalNet(nn.Module):
    """Learned smoothing of the window's poses plus a temporal-convolution correction, in metres."""

    def __init__(self, config: TemporalConfig) -> None:
        """Layers for config.widths; the correction's last layer starts at zero."""
        super().__init__()
        self.config = config
        width, widths = config.channels, config.widths
        self.smooth = nn.Parameter(torch.tensor(initial_kernel(config), dtype=torch.float32))
        self.expand = nn.Conv1d(FEATURES, width, widths[0], bias=False)
        self.expand_norm = nn.BatchNorm1d(width)
        self.convs = nn.ModuleList(nn.Conv1d(width, width, w, bias=False) for w in widths[1:])
        self.mixes = nn.ModuleList(nn.Conv1d(width, width, 1, bias=False) for _ in widths[1:])
        self.conv_norms = nn.ModuleList(nn.BatchNorm1d(width) for _ in widths[1:])
        self.mix_norms = nn.ModuleList(nn.BatchNorm1d(width) for _ in widths[1:])
        self.drop = nn.Dropout(config.dropout)
        self.out = nn.Conv1d(width, POSE_CHANNELS, 1)
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)  # type: ignore[arg-type]  # a Conv1d made with bias=True has one

    def _aligned(self, x: torch.Tensor, length: int) -> torch.Tensor:
        """The `length` frames of x (N, C, L) that answers of the next layer line up with."""
        skip = x.shape[2] - length
        start = skip if self.config.mode == "causal" else skip // 2
        return x[:, :, start : start + length]

    def forward(self, features: torch.Tensor, strided: bool = False) -> torch.Tensor:
        """(N, FEATURES, L) -> (N, L - T + 1, J, 3) metres, one answer per window of T frames.

        strided: for L = T exactly, the same answer with strided convolutions (the frames each layer
        reads, not every frame): what the exported model runs, about 5x cheaper per answer."""
        widths, act = self.config.widths, torch.relu
        h = (
            self.expand(features)
            if not strided
            else nn.functional.conv1d(features, self.expand.weight, stride=widths[0])
        )
        h = self.drop(act(self.expand_norm(h)))
        dilation = widths[0]
        for conv, mix, conv_norm, mix_norm, w in zip(
            self.convs, self.mixes, self.conv_norms, self.mix_norms, widths[1:], strict=True
        ):
            assert isinstance(conv, nn.Conv1d)
            if strided:
                y = nn.functional.conv1d(h, conv.weight, stride=w)
                keep = w - 1 if self.config.mode == "causal" else w // 2
                skip = h[:, :, keep::w]
            else:
                y = nn.functional.conv1d(h, conv.weight, dilation=dilation)
                skip = self._aligned(h, y.shape[2])
            y = self.drop(act(conv_norm(y)))
            h = skip + self.drop(act(mix_norm(mix(y))))
            dilation *= w
        correction = self.out(h)  # (N, 3J, L')
        kernel = self.smooth.view(1, 1, -1).expand(POSE_CHANNELS, 1, -1)
        smoothed = nn.functional.conv1d(features[:, :POSE_CHANNELS], kernel, groups=POSE_CHANNELS)
        answer = smoothed + correction  # (N, 3J, L')
        return answer.transpose(1, 2).reshape(features.shape[0], -1, J, 3)


def slot_weights(slots: int, target: torch.Tensor, fps: torch.Tensor, config: TemporalConfig) -> torch.Tensor:
    """(N, T, K) linear-interpolation weights of K frame slots for the T grid times of a window
    around slot `target` (N,) at `fps` (N,); a time beyond the slots takes the end slot."""
    offsets = (torch.arange(config.window, dtype=fps.dtype) - config.target) / GRID_FPS  # (T,) seconds
    position = (target.unsqueeze(1) + offsets.unsqueeze(0) * fps.unsqueeze(1)).clamp(0.0, slots - 1.0)
    index = torch.arange(slots, dtype=fps.dtype)
    return torch.relu(1.0 - (position.unsqueeze(-1) - index).abs())


class TemporalGraph(nn.Module):
    """What is exported: K frames of one track at `fps` -> the pose of its target frame, mm.

    The service passes the frames around the answered one, evenly spaced in time (a missing frame
    bridged, a window's start or end repeated): causal, the answered frame is slot K - 1; offline,
    slot (K - 1) / 2 with K odd. K may be anything large enough for the window at that rate
    (window_seconds * fps frames); extra slots are never read.
    """

    def __init__(self, net: TemporalNet) -> None:
        """Wrap a trained TemporalNet (put in eval mode by the caller)."""
        super().__init__()
        self.net = net

    def forward(
        self, poses: torch.Tensor, keypoints_2d: torch.Tensor, visibility: torch.Tensor, fps: torch.Tensor
    ) -> torch.Tensor:
        """poses (N, K, J, 3) mm, keypoints_2d (N, K, J, 2) px, visibility (N, K, J), fps (N,) ->
        pose_3d_camera (N, J, 3) mm."""
        config = self.net.config
        slots = poses.shape[1]
        last = torch.full_like(fps, 1.0) * (slots - 1)
        target = last if config.mode == "causal" else last / 2
        weights = slot_weights(slots, target, fps, config)  # (N, T, K)
        seen = (visibility > 0.5).to(poses.dtype)
        grid_poses = torch.einsum("ntk,nkjc->ntjc", weights, poses)
        grid_points = torch.einsum("ntk,nkjc->ntjc", weights, keypoints_2d * seen.unsqueeze(-1))
        grid_seen = (torch.einsum("ntk,nkj->ntj", weights, seen) > 1.0 - 1e-3).to(poses.dtype)
        features = grid_features(grid_poses, grid_points, grid_seen)
        return self.net(features, strided=True)[:, 0] * 1000.0


def slots_needed(config: TemporalConfig, fps: float) -> int:
    """K: the frame slots a window needs at `fps` (odd for offline windows)."""
    span = (config.window - 1) / GRID_FPS * fps  # frames from the window's first grid time to its last
    if config.mode == "causal":
        return math.ceil(span - 1e-6) + 1
    return 2 * math.ceil(span / 2 - 1e-6) + 1
