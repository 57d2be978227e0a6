"""AML's networks: the 3D-conv VAE (prior encoder + decoder) and the observation encoder,
with the named sizes (``PRESETS``) and the voxel grid of each frame.

The paper's stages (two conv + BN + ReLU, max-pool / nearest upsampling) run at half
resolution: the encoders start with a 2 x 2 x 2 space-to-depth of the grid (12 x 27 x 12 x
8C) and the decoder ends with the inverse depth-to-space of a 1 x 1 x 1 convolution, so no
3 x 3 x 3 convolution touches the 31k-voxel full-resolution grid (the CPU budget: <= 5 ms per
car at batch 32 with marching cubes).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from pcc_ros.errors import ConfigError
from pcc_ros.geometry.voxels import AML_GRID, BOX_GRID, GridSpec

PRESETS: dict[str, dict[str, Any]] = {
    "default": {
        "latent": 10,
        "channels": [8, 16, 32],
        "log_var": -2.0,
        "truncation": 3.0,
        "output_points": 2048,
        "max_rays": 256,
        "stop": 1.0,
        # the grid's frame: "box" (the box is [-0.5, 0.5]^3: shapes take the box's width and
        # height) or "canonical" (box length = 1, fixed y / z range; what checkpoints without "frame" used)
        "frame": "box",
    },
}

#: The grid of each frame (``geometry/voxels.py``).
GRIDS: dict[str, GridSpec] = {"box": BOX_GRID, "canonical": AML_GRID}
#: Box aspect (1, w / l, h / l) assumed for a cloud without a box (no SceneContext): the
#: mean of SynthCars' car families (sedan 4.6 x 1.82 x 1.45 m ... van 4.9 x 1.9 x 1.98 m).
DEFAULT_ASPECT = (1.0, 0.41, 0.35)


def grid_of(config: dict[str, Any]) -> GridSpec:
    frame = config.get("frame", "box")
    if frame not in GRIDS:
        raise ConfigError(f"aml: frame must be one of {sorted(GRIDS)}, got {frame!r}")
    return GRIDS[frame]


def _stage(cin: int, cout: int) -> nn.Sequential:
    """Two conv + BN + ReLU (the paper's stage)."""
    return nn.Sequential(
        nn.Conv3d(cin, cout, 3, padding=1, bias=False), nn.BatchNorm3d(cout), nn.ReLU(inplace=True),
        nn.Conv3d(cout, cout, 3, padding=1, bias=False), nn.BatchNorm3d(cout), nn.ReLU(inplace=True),
    )


def space_to_depth(x: torch.Tensor) -> torch.Tensor:
    """``(B, C, 2h, 2l, 2w) -> (B, 8C, h, l, w)``."""
    b, c, h, n, w = x.shape
    x = x.view(b, c, h // 2, 2, n // 2, 2, w // 2, 2).permute(0, 1, 3, 5, 7, 2, 4, 6)
    return x.reshape(b, c * 8, h // 2, n // 2, w // 2)


def depth_to_space(x: torch.Tensor) -> torch.Tensor:
    """``(B, 8C, h, l, w) -> (B, C, 2h, 2l, 2w)`` (inverse of :func:`space_to_depth`)."""
    b, c8, h, n, w = x.shape
    c = c8 // 8
    x = x.view(b, c, 2, 2, 2, h, n, w).permute(0, 1, 5, 2, 6, 3, 7, 4)
    return x.reshape(b, c, h * 2, n * 2, w * 2)


class Encoder(nn.Module):
    """Grid ``(B, C, 24, 54, 24)`` -> ``(B, out)``: space-to-depth, 3 stages with max-pooling, FC."""

    def __init__(self, in_channels: int, channels: Sequence[int], out_dim: int) -> None:
        super().__init__()
        c1, c2, c3 = (int(c) for c in channels)
        self.stage1 = _stage(in_channels * 8, c1)  # 12 x 27 x 12
        self.stage2 = _stage(c1, c2)  # 6 x 14 x 6
        self.stage3 = _stage(c2, c3)  # 3 x 7 x 3
        self.fc = nn.Linear(c3 * 3 * 7 * 3, out_dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.stage1(space_to_depth(x))
        x = self.stage2(F.max_pool3d(x, 2, ceil_mode=True))
        x = self.stage3(F.max_pool3d(x, 2, ceil_mode=True))
        return self.fc(x.flatten(1))


class Decoder(nn.Module):
    """``z (B, Q)`` -> ``(B, 2, 24, 54, 24)``: occupancy logits and SDF means (voxels)."""

    def __init__(self, latent: int, channels: Sequence[int]) -> None:
        super().__init__()
        c1, c2, c3 = (int(c) for c in channels)
        self.c3 = c3
        self.fc = nn.Linear(latent, c3 * 3 * 7 * 3)
        self.stage3 = _stage(c3, c3)  # 3 x 7 x 3
        self.stage2 = _stage(c3, c2)  # 6 x 14 x 6
        self.stage1 = _stage(c2, c1)  # 12 x 28 x 12
        self.out = nn.Conv3d(c1, 2 * 8, 1)  # depth-to-space -> 2 x 24 x 56 x 24

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        x = F.relu(self.fc(z)).view(-1, self.c3, 3, 7, 3)
        x = self.stage3(x)
        x = self.stage2(F.interpolate(x, scale_factor=2, mode="nearest"))
        x = self.stage1(F.interpolate(x, scale_factor=2, mode="nearest"))
        return depth_to_space(self.out(x))[:, :, :, 1:55, :]


class AMLNet(nn.Module):
    """The VAE (``prior_encoder`` + ``decoder``) and AML's observation ``encoder``.

    ``freeze_decoder()`` fixes the decoder's weights *and* its batch-norm statistics
    (it stays in eval mode whatever ``train()`` is called with).
    """

    def __init__(self, latent: int, channels: Sequence[int]) -> None:
        super().__init__()
        self.latent = int(latent)
        self.prior_encoder = Encoder(2, channels, 2 * self.latent)
        self.encoder = Encoder(2, channels, self.latent)
        self.decoder = Decoder(self.latent, channels)
        self.decoder_frozen = False

    def freeze_decoder(self) -> None:
        self.decoder_frozen = True
        for p in self.decoder.parameters():
            p.requires_grad_(False)
        self.decoder.eval()

    def train(self, mode: bool = True) -> AMLNet:
        super().train(mode)
        if self.decoder_frozen:
            self.decoder.eval()
        return self

    def forward(self, grids: torch.Tensor, prior: bool = False) -> tuple[torch.Tensor, ...]:
        """Observation grids ``(B, 2, H, L, W)`` -> ``(z, decoded)``; with ``prior``: reference
        grids (occupancy, SDF / truncation) -> ``(mu, logvar, decoded)`` of the VAE (a sample
        of ``q(z|y)`` in training mode, its mean in eval mode)."""
        if not prior:
            z = self.encoder(grids)
            return z, self.decoder(z)
        mu, logvar = self.prior_encoder(grids).chunk(2, dim=1)
        logvar = logvar.clamp(-10.0, 10.0)
        z = mu + torch.randn_like(mu) * torch.exp(0.5 * logvar) if self.training else mu
        return mu, logvar, self.decoder(z)
