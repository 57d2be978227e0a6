"""AML: amortized maximum likelihood shape completion (Stutz & Geiger, ``shared/papers/aml.txt``).

Two steps, as in the paper (Fig. 2):

1. **Shape prior** (Eq. 1-3). A 3D-conv VAE on reference shapes: SynthCars' complete
   canonical car surfaces voxelised to occupancy + SDF grids (``geometry/voxels.py``), two
   channels, 24 x 54 x 24 (H x L x W). Recognition model ``q(z|y) = N(mu(y), diag sigma^2(y))``,
   ``Q = 10``; generative model ``p(y_i|z)``: Bernoulli occupancy (sigmoid logits) and
   Gaussian SDF with ``log sigma^2 = -2``. Loss: BCE + Gaussian NLL + KL, one sample per step,
   light rotation / scale / translation augmentation of the grids.
2. **Amortized ML** (Eq. 5). The decoder is frozen; a new deterministic encoder ``z(x; w)``
   maps an *observation* (occupied / ray-cast free / unknown voxels of a partial scan) to a
   latent code, trained on partial observations only with the negative log-likelihood of the
   observed voxels (occupied = 1, free = 0) plus ``lambda * ||z||^2 / 2``. For the SDF
   channel the observation's likelihood is ``P(sdf <= 0) = Phi(-mu / sigma)`` (the paper's
   reparameterisation), so both channels give a cross-entropy. ``lambda`` is chosen on a
   validation split by the ML baseline (below) and recorded in the checkpoint.

**ML baseline** (Eq. 4): the same objective minimised per instance over ``z`` by Adam from
the prior mean, batched over instances (backend ``aml_ml``, same weights).

Output: marching cubes (scikit-image) on the decoded SDF of the whole batch in one call, a
triangle mesh per instance, ``output_points`` points sampled uniformly by area on it (seeded
by the input cloud's content), in the canonical frame.

Architecture (paper: three stages of two conv + BN + ReLU with max-pool / nearest
upsampling). For the CPU budget (<= 5 ms per car at batch 32 with marching cubes) the stages
run at half resolution: the encoders start with a 2 x 2 x 2 space-to-depth of the grid
(12 x 27 x 12 x 8C) and the decoder ends with the inverse depth-to-space of a 1 x 1 x 1
convolution, so no 3 x 3 x 3 convolution touches the 31k-voxel full-resolution grid.
"""

from __future__ import annotations

import json
import logging
import math
import zlib
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from scipy.spatial import cKDTree
from torch import nn
from tqdm import tqdm

from pcc_ros.errors import CheckpointError, ConfigError, DataError
from pcc_ros.files import atomic_write
from pcc_ros.geometry.canonical import to_canonical
from pcc_ros.geometry.voxels import (
    AML_GRID,
    BOX_GRID,
    GridSpec,
    box_aspect,
    estimate_origin,
    from_box_frame,
    observation_grids,
    reference_grids,
    to_box_frame,
)
from pcc_ros.metrics import instance_metrics
from pcc_ros.models.base import ASPECT_SCALE_RANGE, SceneContext, TorchCompleter, TrainingKit, cloud_seed
from pcc_ros.models.checkpoint import load_checkpoint
from pcc_ros.models.registry import register

log = logging.getLogger(__name__)

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
        # height) or "canonical" (box length = 1, fixed y / z range; the first shipped weights)
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


# --------------------------------------------------------------------------- network


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


# --------------------------------------------------------------------------- likelihoods


def observed_nll(decoded: torch.Tensor, occupied: torch.Tensor, free: torch.Tensor, log_var: float) -> torch.Tensor:
    """``-sum_{x_i != ⊥} ln p(y_i = x_i | z)`` per instance, both channels (Eq. 4/5 data term).

    Occupancy: Bernoulli with the decoded logits. SDF: ``P(occupied) = Phi(-mu / sigma)``.
    """
    target = occupied.to(decoded.dtype)
    mask = (occupied | free).to(decoded.dtype)
    logits, mu = decoded[:, 0], decoded[:, 1]
    occ = F.binary_cross_entropy_with_logits(logits, target, reduction="none")
    s = mu / math.exp(0.5 * log_var)
    sdf = -(target * torch.special.log_ndtr(-s) + (1 - target) * torch.special.log_ndtr(s))
    return ((occ + sdf) * mask).flatten(1).sum(1)


def reference_nll(decoded: torch.Tensor, occupancy: torch.Tensor, sdf: torch.Tensor, log_var: float) -> torch.Tensor:
    """``-ln p(y | z)`` per instance: Bernoulli occupancy + Gaussian SDF (Eq. 2), constants dropped."""
    occ = F.binary_cross_entropy_with_logits(decoded[:, 0], occupancy, reduction="none")
    gauss = 0.5 * (decoded[:, 1] - sdf) ** 2 / math.exp(log_var)
    return (occ + gauss).flatten(1).sum(1)


# --------------------------------------------------------------------------- meshes


def _stacked_marching_cubes(sdf: np.ndarray, spec: GridSpec, level: float, allow_degenerate: bool
                            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One marching-cubes call on a batch of SDF grids stacked along the height axis, each
    wrapped in a one-voxel layer of "outside" (meshes closed at the grid border, no triangle
    joining two instances). Returns grid-frame vertices ``(V, 3)``, faces ``(F, 3)`` (global
    vertex indices) and each vertex's instance; empty arrays when nothing crosses ``level``."""
    from skimage.measure import marching_cubes

    b, h, n, w = sdf.shape
    outside = float(max(np.abs(sdf).max(), 1.0)) if sdf.size else 1.0
    padded = np.full((b, h + 2, n + 2, w + 2), outside, dtype=np.float32)
    padded[:, 1:-1, 1:-1, 1:-1] = sdf
    volume = padded.reshape(b * (h + 2), n + 2, w + 2)
    if not (volume.min() < level < volume.max()):
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros(0, np.int64)
    verts, faces, _, _ = marching_cubes(volume, level=level, method="lewiner", allow_degenerate=allow_degenerate)
    owner = np.floor(verts[:, 0] / (h + 2)).astype(np.int64)
    local = verts - np.stack([owner * (h + 2) + 1, np.ones_like(owner), np.ones_like(owner)], axis=1)
    return spec.from_hlw(local), faces.astype(np.int64), owner


def marching_cubes_batch(sdf: np.ndarray, spec: GridSpec = AML_GRID, level: float = 0.0
                         ) -> list[tuple[np.ndarray, np.ndarray]]:
    """Meshes of the zero level sets of a batch of SDF grids, in one marching-cubes call
    (:func:`_stacked_marching_cubes`; degenerate triangles removed).

    Returns:
        per instance ``(vertices (V, 3) in the grid's frame float64, faces (F, 3) int64)``; an
        instance without a surface gets empty arrays.
    """
    b = len(sdf)
    canonical, faces, owner = _stacked_marching_cubes(sdf, spec, level, allow_degenerate=False)
    empty = (np.zeros((0, 3)), np.zeros((0, 3), np.int64))
    if len(faces) == 0:
        return [empty] * b
    face_owner = owner[faces[:, 0]]
    order = np.argsort(face_owner, kind="stable")
    faces, face_owner = faces[order], face_owner[order]
    v_counts = np.bincount(owner, minlength=b)
    v_start = np.cumsum(v_counts) - v_counts
    v_order = np.argsort(owner, kind="stable")  # vertices are emitted block by block; be sure
    rank = np.empty_like(v_order)
    rank[v_order] = np.arange(len(v_order))
    f_bounds = np.searchsorted(face_owner, np.arange(b + 1))
    out = []
    for i in range(b):  # split per instance (slicing only)
        if v_counts[i] == 0:
            out.append(empty)
            continue
        f = rank[faces[f_bounds[i]:f_bounds[i + 1]]] - v_start[i]
        out.append((canonical[v_order[v_start[i]:v_start[i] + v_counts[i]]], f.astype(np.int64)))
    return out


def _sample_faces(verts: np.ndarray, faces: np.ndarray, face_owner: np.ndarray, count: int, n: int,
                  seeds: Sequence[int]) -> list[np.ndarray]:
    """``n`` points uniform by area on the faces of each of ``count`` instances (faces of all
    instances in one array, ``face_owner`` their instance); the draws of an instance depend
    only on its seed. An instance without faces (or area) gets an empty array."""
    if len(faces) == 0:
        return [np.zeros((0, 3), np.float32) for _ in range(count)]
    if (np.diff(face_owner) < 0).any():  # marching cubes emits them in order; be sure
        order = np.argsort(face_owner, kind="stable")
        faces, face_owner = faces[order], face_owner[order]
    a = verts[faces[:, 0]]
    e1 = verts[faces[:, 1]] - a
    e2 = verts[faces[:, 2]] - a
    cross = np.stack([e1[:, 1] * e2[:, 2] - e1[:, 2] * e2[:, 1], e1[:, 2] * e2[:, 0] - e1[:, 0] * e2[:, 2],
                      e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]], axis=1)
    area = 0.5 * np.sqrt(np.einsum("ij,ij->i", cross, cross))
    cum = np.cumsum(area)
    total = np.bincount(face_owner, weights=area, minlength=count)
    start = np.concatenate([[0.0], cum])[np.searchsorted(face_owner, np.arange(count))]
    u = np.stack([np.random.default_rng(s).random((n, 3)) for s in seeds])  # (B, n, 3)
    face = np.clip(np.searchsorted(cum, start[:, None] + u[..., 0] * total[:, None], side="right"), 0, len(cum) - 1)
    r1 = np.sqrt(u[..., 1:2])
    points = (a[face] + r1 * (1 - u[..., 2:3]) * e1[face] + r1 * u[..., 2:3] * e2[face]).astype(np.float32)
    return [points[i] if total[i] > 0 else np.zeros((0, 3), np.float32) for i in range(count)]


def sample_meshes(meshes: Sequence[tuple[np.ndarray, np.ndarray]], n: int, seeds: Sequence[int]) -> list[np.ndarray]:
    """``n`` points uniform by area on each mesh, all meshes in one vectorised pass.

    ``seeds``: one per mesh (the draws of a mesh depend only on its seed). A mesh without
    faces gives an empty array.
    """
    if not meshes:
        return []
    sizes = np.array([len(v) for v, _ in meshes])
    offsets = np.cumsum(sizes) - sizes
    verts = np.concatenate([np.asarray(v, np.float64).reshape(-1, 3) for v, _ in meshes])
    faces = np.concatenate([np.asarray(f, np.int64).reshape(-1, 3) + o for (_, f), o in zip(meshes, offsets)])
    owner = np.repeat(np.arange(len(meshes)), [len(f) for _, f in meshes])
    return _sample_faces(verts, faces, owner, len(meshes), n, seeds)


def surface_samples(sdf: np.ndarray, spec: GridSpec, aspects: np.ndarray, n: int, seeds: Sequence[int],
                    level: float = 0.0) -> list[np.ndarray]:
    """Decoded SDF grids -> ``n`` canonical points uniform by area on each zero level set: one
    marching-cubes call for the batch, each mesh stretched from the grid's frame by its
    ``aspects`` row, sampled without splitting the batch into meshes. Degenerate (zero-area)
    triangles are kept: they are never drawn."""
    verts, faces, owner = _stacked_marching_cubes(sdf, spec, level, allow_degenerate=True)
    if len(faces) == 0:
        return [np.zeros((0, 3), np.float32) for _ in range(len(sdf))]
    return _sample_faces(from_box_frame(verts, np.asarray(aspects, np.float64)[owner]), faces, owner[faces[:, 0]],
                         len(sdf), n, seeds)


# --------------------------------------------------------------------------- completer


def box_aspects(contexts: Sequence[SceneContext | None]) -> np.ndarray:
    """``(B, 3)`` box aspect ``(1, w / l, h / l)`` of each instance: its context's box, else
    :data:`DEFAULT_ASPECT`; ``w / l`` and ``h / l`` clipped to ``ASPECT_SCALE_RANGE`` times the
    default (as the shared :func:`~pcc_ros.models.base.aspect_scales`): a detector box twice
    as wide or tall as a car is not a car body the prior can fill."""
    default = np.asarray(DEFAULT_ASPECT, np.float64)
    out = np.tile(default, (len(contexts), 1))
    for i, ctx in enumerate(contexts):  # per instance: one 3-vector
        if ctx is not None:
            out[i] = box_aspect(ctx.box.size[0])
    low, high = ASPECT_SCALE_RANGE
    out[:, 1:] = np.clip(out[:, 1:], default[1:] * low, default[1:] * high)
    return out


def canonical_origins(clouds: Sequence[np.ndarray], contexts: Sequence[SceneContext | None]) -> np.ndarray:
    """Sensor origin of each cloud in its canonical frame: exact from a context's box, else estimated."""
    out = np.empty((len(clouds), 3))
    for i, (cloud, ctx) in enumerate(zip(clouds, contexts)):  # per instance: one 3-vector
        if ctx is None:
            out[i] = estimate_origin(cloud)
        else:
            box = ctx.box
            out[i] = to_canonical(ctx.sensor_origin[None], box.center[0], float(box.yaw[0]), float(box.size[0, 0]))[0]
    return out


@register("aml")
class AML(TorchCompleter):
    """AML completer: canonical partial clouds (+ sensor origin via the scene context) in,
    ``output_points`` canonical points on the decoded car surface out.

    Without a :class:`SceneContext` the sensor origin (for free space) is estimated from
    the side the points face (:func:`~pcc_ros.geometry.voxels.estimate_origin`).
    """

    uses_context = True
    #: Per-instance optimisation of z instead of the amortized encoder (the ML baseline).
    inference = "aml"

    #: The named sizes of the network.
    presets = PRESETS

    def __init__(self, device: str = "auto", **options: Any) -> None:
        #: lambda of Eq. 4/5 (set from the checkpoint; training selects it on validation).
        self.lam = 1.0
        self.ml_steps = 40
        self.ml_lr = 0.15
        # options: size (a preset), hyper-parameters overriding it, and run-time options (batch_size, ...)
        super().__init__(device=device, **options)

    def build_model(self) -> AMLNet:
        if len(self.config["channels"]) != 3:
            raise ConfigError(f"aml: channels must list three stage widths, got {self.config['channels']}")
        # channels-last 3D: oneDNN's preferred convolution layout on CPU
        return AMLNet(int(self.config["latent"]), self.config["channels"]).to(memory_format=torch.channels_last_3d)

    # ---- checkpoints: lambda is "training.lam" in the JSON config (chosen after the
    # model is built, so it is not a constructor hyper-parameter)

    def save(self, path: str | Path, *, training: dict[str, Any] | None = None,
             metrics: dict[str, Any] | None = None, extra: dict[str, Any] | None = None) -> Path:
        return super().save(path, training={**(training or {}), "lam": self.lam}, metrics=metrics, extra=extra)

    @classmethod
    def from_checkpoint(cls, path: str | Path, device: str = "auto", **overrides: Any) -> AML:
        completer = super().from_checkpoint(path, device=device, **overrides)
        lam = (completer.checkpoint_config or {}).get("training", {}).get("lam")
        if lam is not None:
            if not (isinstance(lam, (int, float)) and lam >= 0):
                raise CheckpointError(f"{path}: invalid lambda {lam!r}")
            completer.lam = float(lam)
        return completer

    # ---- inference

    def points_per_car(self) -> int:
        """Points sampled on each mesh: ``output_points``, times the point multiplier a 2 x 2
        folding grid gets at the run-time ``decode_density`` d, ((d + 1) / 2)^2 (2.25 at the node's
        default 2): the same denser output as the folding backends, drawn on the same mesh."""
        d = int(getattr(self, "decode_density", 1))
        return round(int(self.config["output_points"]) * ((d + 1) / 2) ** 2)

    @property
    def grid(self) -> GridSpec:
        """The voxel grid of this model's frame (``frame`` hyper-parameter)."""
        return grid_of(self.config)

    def aspects(self, contexts: Sequence[SceneContext | None]) -> np.ndarray:
        """``(B, 3)`` scale from the grid's frame to the canonical frame (ones for ``frame: canonical``)."""
        if self.config.get("frame", "box") == "canonical":
            return np.ones((len(contexts), 3))
        return box_aspects(contexts)

    def observe(self, clouds: Sequence[np.ndarray], contexts: Sequence[SceneContext | None]
                ) -> tuple[torch.Tensor, np.ndarray]:
        """``(B, 2, H, L, W)`` float observation grids (occupied, free) on the model's device, and
        the ``(B, 3)`` aspects that map the grid's frame back to the canonical one."""
        aspects = self.aspects(contexts)
        return self.observe_frame(clouds, canonical_origins(clouds, contexts), aspects), aspects

    def observe_frame(self, clouds: Sequence[np.ndarray], origins: np.ndarray, aspects: np.ndarray) -> torch.Tensor:
        """Observation grids of canonical clouds with canonical sensor ``origins`` and box ``aspects``."""
        occupied, free = observation_grids([to_box_frame(c, a) for c, a in zip(clouds, aspects)],
                                           to_box_frame(origins, aspects), self.grid,
                                           stop=float(self.config["stop"]), max_rays=int(self.config["max_rays"]))
        # built channels-last (B, H, L, W, 2) and viewed as (B, 2, H, L, W): oneDNN's layout, no copy
        grids = np.empty((*occupied.shape, 2), np.float32)
        grids[..., 0], grids[..., 1] = occupied, free
        return torch.from_numpy(grids).permute(0, 4, 1, 2, 3).to(self.device)

    def decode_points(self, decoded: torch.Tensor, clouds: Sequence[np.ndarray], aspects: np.ndarray
                      ) -> list[np.ndarray]:
        """Decoded grids -> marching cubes on the SDF -> surface samples (one canonical cloud each)."""
        sdf = decoded[:, 1].float().cpu().numpy()
        points = surface_samples(sdf, self.grid, aspects, self.points_per_car(),
                                 [cloud_seed(c) for c in clouds])
        missing = [i for i, p in enumerate(points) if len(p) == 0]
        if missing:  # no zero crossing: fall back to the decoded occupancy, then the input
            log.warning("aml: %d decoded shape(s) without a surface; using occupied voxels", len(missing))
            occ = decoded[:, 0].float().cpu().numpy() > 0
            centres = self.grid.centers()
            for i in missing:
                points[i] = (from_box_frame(centres[occ[i]], aspects[i]).astype(np.float32) if occ[i].any()
                             else np.asarray(clouds[i], np.float32))
        return points

    def forward_batch(self, clouds: list[np.ndarray], contexts: list[SceneContext | None]) -> list[np.ndarray]:
        x, aspects = self.observe(clouds, contexts)
        if self.inference == "ml":
            z = self.fit_latent(x[:, 0] > 0.5, x[:, 1] > 0.5)
            decoded = self.model.decoder(z.to(next(self.model.decoder.parameters()).dtype))
        else:
            _, decoded = self.model(x)
        return self.decode_points(decoded, clouds, aspects)

    def fit_latent(self, occupied: torch.Tensor, free: torch.Tensor, steps: int | None = None,
                   lam: float | None = None) -> torch.Tensor:
        """Eq. 4: ``argmin_z`` of the observed-voxel NLL + ``lam ||z||^2 / 2`` by Adam, from ``z = 0``.

        Batched over instances (the objective is a sum of independent per-instance terms).
        """
        lam = self.lam if lam is None else float(lam)
        steps = self.ml_steps if steps is None else int(steps)
        decoder = self.model.decoder
        was_training = decoder.training
        decoder.eval()
        with torch.inference_mode(False), torch.enable_grad():
            occ, fr = occupied.clone(), free.clone()
            z = torch.zeros(len(occ), self.model.latent, device=occ.device, requires_grad=True)
            opt = torch.optim.Adam([z], lr=self.ml_lr)
            params = [p.requires_grad for p in decoder.parameters()]
            for p in decoder.parameters():
                p.requires_grad_(False)
            try:
                dtype = next(decoder.parameters()).dtype
                for _ in range(steps):
                    loss = (observed_nll(decoder(z.to(dtype)).float(), occ, fr, float(self.config["log_var"]))
                            + lam * 0.5 * (z**2).sum(1)).sum()
                    opt.zero_grad(set_to_none=True)
                    loss.backward()
                    opt.step()
            finally:
                for p, flag in zip(decoder.parameters(), params):
                    p.requires_grad_(flag)
                decoder.train(was_training)
        return z.detach()


@register("aml_ml")
class AMLMaximumLikelihood(AML):
    """The ML baseline of AML (Eq. 4): same prior and objective, ``z`` optimised per instance.

    Loads AML's checkpoints (the decoder and lambda); the amortized encoder is not used.
    """

    inference = "ml"
    weights_name = "aml"


# --------------------------------------------------------------------------- training data


@dataclass
class ReferenceSet:
    """Voxelised reference shapes (the prior's training data): occupancy and SDF grids."""

    occupancy: np.ndarray  # (M, H, L, W) bool
    sdf: np.ndarray  # (M, H, L, W) float32, voxels
    keys: list[str] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.occupancy)

    def subset(self, index: np.ndarray) -> ReferenceSet:
        return ReferenceSet(self.occupancy[index], self.sdf[index], [self.keys[i] for i in index])


def shape_to_grid_frame(surface: np.ndarray, frame: str) -> np.ndarray:
    """A canonical complete shape in the grid's frame: for ``box``, centred on its bounding box
    and divided by its extent (SynthCars' boxes are exactly their shapes' bounding boxes)."""
    pts = np.asarray(surface, np.float64)[:, :3]
    if frame == "canonical":
        return pts
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    extent = hi - lo
    if not (extent > 1e-6).all():
        raise DataError(f"degenerate reference shape (extent {extent.tolist()})")
    return to_box_frame(pts - (lo + hi) / 2, extent)  # x extent is 1 (canonical) for SynthCars


def synthcars_reference_shapes(root: str | Path, truncation: float, max_shapes: int | None = None, seed: int = 0,
                               progress: bool = True, frame: str = "box") -> ReferenceSet:
    """Voxelise the complete shapes of a SynthCars root's *train* sequences (test never);
    at most ``max_shapes`` of them (a seeded subset), in the grid of ``frame``."""
    root = Path(root)
    meta_path = root / "meta.json"
    if not (meta_path.is_file() and (root / "shapes").is_dir()):
        raise DataError(f"{root}: not a SynthCars root (needs meta.json and shapes/); "
                        "`pcc train aml --stage prior` reads the reference shapes from one")
    try:
        splits = json.loads(meta_path.read_text())["splits"]
        train = [str(s) for s in splits["train"]]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise DataError(f"{meta_path}: unreadable SynthCars meta.json ({exc})") from exc
    files = sorted(p for s in train for p in (root / "shapes" / s).glob("*.npy"))
    if not files:
        raise DataError(f"{root}/shapes: no shapes of the train sequences")
    if max_shapes is not None and len(files) > max_shapes:
        pick = np.sort(np.random.default_rng(seed).choice(len(files), max_shapes, replace=False))
        files = [files[i] for i in pick]
    occ, sdf, keys = [], [], []
    skipped = 0
    for path in tqdm(files, desc="voxelise reference shapes", unit="shape", disable=not progress):
        try:
            surface = shape_to_grid_frame(np.load(path, allow_pickle=False), frame)
            o, s = reference_grids(surface, GRIDS[frame], truncation)
        except (OSError, ValueError, DataError) as exc:
            log.warning("skipping reference shape %s: %s", path, exc)
            skipped += 1
            continue
        occ.append(o)
        sdf.append(s)
        keys.append(f"{path.parent.name}/{path.stem}")
    if skipped:
        log.info("skipped %d unreadable reference shape(s)", skipped)
    return ReferenceSet(np.stack(occ), np.stack(sdf), keys)


def _hash_split(keys: Sequence[str], val_fraction: float) -> np.ndarray:
    return np.array([zlib.crc32(k.encode()) / 2**32 < val_fraction for k in keys], dtype=bool)


@dataclass
class PriorBatch:
    occupancy: torch.Tensor  # (B, H, L, W) float
    sdf: torch.Tensor

    def to(self, device: torch.device) -> PriorBatch:
        return PriorBatch(self.occupancy.to(device), self.sdf.to(device))


def augment_grids(occupancy: torch.Tensor, sdf: torch.Tensor, rng: np.random.Generator, rotation_deg: float = 4.0,
                  scale: float = 0.05, shift_voxels: float = 1.0, spec: GridSpec = AML_GRID,
                  axis_scale: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Light random yaw rotation, scale and translation of reference grids (trilinear).

    Each output voxel at ``p`` samples the input at ``R(yaw) p / s + t``; ``s`` is one
    isotropic factor in ``1 +- scale`` times a per-axis factor in ``1 +- axis_scale`` (a car
    that does not fill its box exactly, as real and detected boxes are). The yaw is applied
    in the grid's own frame.
    """
    b = len(occupancy)
    yaw = np.deg2rad(rng.uniform(-rotation_deg, rotation_deg, b))
    s = rng.uniform(1 - scale, 1 + scale, b)[:, None] * rng.uniform(1 - axis_scale, 1 + axis_scale, (b, 3))
    shift = rng.uniform(-shift_voxels, shift_voxels, (b, 3)) * spec.voxel_size
    a = np.zeros((b, 3, 3))
    a[:, 0, 0], a[:, 0, 1], a[:, 1, 0], a[:, 1, 1] = np.cos(yaw), -np.sin(yaw), np.sin(yaw), np.cos(yaw)
    a[:, 2, 2] = 1.0
    a /= s[:, :, None]
    half = (np.asarray(spec.upper) - np.asarray(spec.lower)) / 2  # grid is centred on 0
    m = a * half[None, None, :] / half[None, :, None]  # in coordinates normalised to [-1, 1]
    t = shift / half
    perm = [1, 0, 2]  # grid_sample's (x, y, z) index the (W, H, D) = (y, x, z) axes of our (h, l, w) arrays
    theta = np.concatenate([m[:, perm][:, :, perm], t[:, perm, None]], axis=2)
    grid = F.affine_grid(torch.from_numpy(theta).float(), [b, 1, *spec.resolution], align_corners=False)
    out = F.grid_sample(torch.stack([occupancy, sdf], 1), grid, mode="bilinear", padding_mode="border",
                        align_corners=False)
    return (out[:, 0] > 0.5).float(), out[:, 1]


@dataclass
class ObservationBatch:
    occupied: torch.Tensor  # (B, H, L, W) bool
    free: torch.Tensor

    def to(self, device: torch.device) -> ObservationBatch:
        return ObservationBatch(self.occupied.to(device), self.free.to(device))

    def grids(self) -> torch.Tensor:
        return torch.stack([self.occupied, self.free], 1).float().contiguous(memory_format=torch.channels_last_3d)


@dataclass
class Observations:
    """Partial observations for the encoder: canonical clouds, their sensor origins (canonical)
    and box aspects ``(1, w / l, h / l)``."""

    clouds: list[np.ndarray]
    origins: np.ndarray
    sources: dict[str, int]
    aspects: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.clouds)


class AMLRecipe:
    """``pcc train aml --stage prior|encoder`` (driven by :mod:`pcc_ros.train`).

    * ``prior``: ``--data`` is a SynthCars root; the VAE learns the voxelised complete shapes
      of its train sequences (90 % / 10 % hash split into train / validation shapes).
      Validation: the VAE loss and the reconstruction IoU of the held-out shapes.
    * ``encoder``: ``--data`` is an instance cache of partial observations, plus ``real``
      (comma-separated caches of real KITTI / nuScenes crops); ``prior`` names the prior
      checkpoint. The decoder is loaded and frozen; lambda is chosen first by the ML
      baseline on validation instances among ``lambdas``; validation: the evaluation
      metrics of the encoder (``val_cd_l1``) on the validation split.
    """

    default_lr = 1e-3

    def __init__(self, size: str = "default", stage: str = "prior", prior: str | None = None,
                 lambdas: str | Sequence[float] = (0.1, 1.0, 10.0), lam: float | None = None,
                 real: str | None = None, real_repeat: int = 4, lambda_instances: int = 96,
                 lambda_steps: int = 40, beta: float = 1.0, augment: bool = True, max_shapes: int = 600,
                 reference_cache: str | None = None, real_split: str = "train", box_jitter: float = 0.06,
                 lambda_real_weight: float = 0.5, lambda_holdout: float = 0.3) -> None:
        if stage not in ("prior", "encoder"):
            raise ConfigError(f"aml: --stage must be prior or encoder, got {stage!r}")
        if stage == "encoder" and not prior:
            raise ConfigError("aml --stage encoder needs the prior: --option prior=RUN/aml.safetensors")
        self.size, self.stage, self.prior = size, stage, prior
        if isinstance(lambdas, str):
            lambdas = [float(v) for v in lambdas.split(",") if v.strip()]
        self.lambdas = [float(v) for v in lambdas]
        self.fixed_lam = lam
        self.real = [p for p in (real or "").split(",") if p.strip()]
        self.real_repeat = int(real_repeat)
        self.lambda_instances = int(lambda_instances)
        self.lambda_steps = int(lambda_steps)
        self.beta = float(beta)
        self.augment = bool(augment)
        self.max_shapes = int(max_shapes)
        self.reference_cache = reference_cache
        if real_split not in ("train", "val", "test", "all"):
            raise ConfigError(f"aml: real_split must be train, val, test or all, got {real_split!r}")
        self.real_split = real_split
        self.box_jitter = float(box_jitter)
        if not 0 <= self.box_jitter < 0.5:
            raise ConfigError(f"aml: box_jitter must be in [0, 0.5), got {box_jitter}")
        self.lambda_real_weight = float(lambda_real_weight)
        self.lambda_holdout = float(lambda_holdout)
        if not 0 < self.lambda_holdout < 1:
            raise ConfigError(f"aml: lambda_holdout must be in (0, 1), got {lambda_holdout}")
        self.select_metric = "val_loss" if stage == "prior" else "val_cd_l1"
        self.lambda_sweep: dict[str, Any] = {}
        self.completer: AML | None = None
        self._source_root: Path | None = None
        #: instance caches and the evaluation-metric validation come through :class:`TrainingKit`
        #: (set by ``pcc_ros.train``); the prior stage needs none of it
        self.kit: TrainingKit | None = None

    def describe(self) -> dict[str, Any]:
        return {"size": self.size, "stage": self.stage, "prior": self.prior, "lambdas": self.lambdas,
                "lam": self.fixed_lam, "real": self.real, "real_repeat": self.real_repeat, "beta": self.beta,
                "augment": self.augment, "lambda_instances": self.lambda_instances,
                "lambda_steps": self.lambda_steps, "max_shapes": self.max_shapes, "real_split": self.real_split,
                "box_jitter": self.box_jitter, "lambda_real_weight": self.lambda_real_weight,
                "lambda_holdout": self.lambda_holdout}

    # ---- model

    def build_completer(self, device: str) -> AML:
        completer = AML(device=device, size=self.size)
        if self.stage == "encoder":
            state, config = load_checkpoint(self.prior)
            if config["backend"] != "aml":
                raise CheckpointError(f"{self.prior}: not an AML checkpoint (backend {config['backend']!r})")
            if config.get("hyper_parameters") != completer.config:
                raise CheckpointError(f"{self.prior}: prior was trained with another model config")
            prior_state = {k: v for k, v in state.items() if not k.startswith("encoder.")}
            missing, unexpected = completer.model.load_state_dict(prior_state, strict=False)
            if unexpected or any(not k.startswith("encoder.") for k in missing):
                raise CheckpointError(f"{self.prior}: prior weights do not fit ({missing[:3]} {unexpected[:3]})")
            completer.model.freeze_decoder()
        self.completer = completer
        return completer

    # ---- data

    def open_data(self, path: Path) -> Any:
        if self.stage == "prior":
            return self._reference_shapes(Path(path))

        return TrainingKit.require(self.kit, "aml").open_cache(path)

    def _reference_shapes(self, root: Path) -> ReferenceSet:
        """The voxelised reference set, read from / written to ``reference_cache`` when given."""
        truncation = float(PRESETS[self.size]["truncation"])
        frame = str(PRESETS[self.size]["frame"])
        cache = Path(self.reference_cache) if self.reference_cache else None
        stamp = f"{root.resolve()}|{self.max_shapes}|{truncation}|{frame}|{GRIDS[frame]}|sdf-voxel-steps"
        if cache is not None and cache.is_file():
            with np.load(cache, allow_pickle=False) as z:
                if str(z["stamp"]) == stamp:
                    log.info("aml: reference grids from %s", cache)
                    return ReferenceSet(z["occupancy"], z["sdf"], [str(k) for k in z["keys"]])
            log.info("aml: %s was made from other shapes or settings; recomputing", cache)
        ref = synthcars_reference_shapes(root, truncation, self.max_shapes, frame=frame)
        if cache is not None:
            cache.parent.mkdir(parents=True, exist_ok=True)
            with atomic_write(cache, "wb") as stream:
                np.savez_compressed(stream, occupancy=ref.occupancy, sdf=ref.sdf, keys=np.array(ref.keys), stamp=stamp)
        return ref

    def training_data(self, source: Any, split: str, min_points: int = 10) -> Any:
        if self.stage == "prior":
            val = _hash_split(source.keys, 0.1)
            return source.subset(np.flatnonzero(~val))

        clouds, origins, aspects, sources = [], [], [], {}
        open_cache = TrainingKit.require(self.kit, "aml").open_cache if self.real else None
        caches = [(source, 1, split)] + [(open_cache(p), self.real_repeat, self.real_split) for p in self.real]
        for cache, repeat, which in caches:  # a handful of caches
            idx = cache.indices(which, min_points=min_points) if which != "all" else np.concatenate(
                [cache.indices(s, min_points=min_points) for s in ("train", "val", "test")])
            pts = [np.asarray(cache.points(int(i)), np.float32) for i in idx]
            sources[str(cache.root)] = len(idx)
            for _ in range(repeat):  # real crops are few: repeated so a batch sees them
                clouds.extend(pts)
                origins.append(cache.meta["origin"][idx].astype(np.float64))
                aspects.append(box_aspect(cache.meta["box_size"][idx]))
        if not clouds:
            raise ConfigError(f"aml: no training observations in split {split!r}")
        return Observations(clouds, np.concatenate(origins), sources, np.concatenate(aspects))

    def batches(self, data: Any, batch_size: int, cfg: dict[str, Any], rng: np.random.Generator) -> Iterator[Any]:
        n = len(data)
        if n == 0:
            raise ConfigError("aml: empty training set")
        while True:
            order = rng.permutation(n) if n >= batch_size else rng.integers(n, size=batch_size)
            for start in range(0, len(order) - batch_size + 1, batch_size):
                pick = order[start:start + batch_size]
                if self.stage == "prior":
                    occ = torch.from_numpy(data.occupancy[pick].astype(np.float32))
                    sdf = torch.from_numpy(data.sdf[pick])
                    if self.augment:
                        occ, sdf = augment_grids(occ, sdf, rng, spec=grid_of(cfg),
                                                 axis_scale=self.box_jitter if cfg.get("frame") == "box" else 0.0)
                    yield PriorBatch(occ.contiguous(), sdf.contiguous())
                else:
                    yield self.observation_batch(data, pick, cfg, rng)

    def observation_batch(self, data: Observations, pick: np.ndarray, cfg: dict[str, Any],
                          rng: np.random.Generator) -> ObservationBatch:
        """Observation grids of ``data[pick]`` in the grid's frame. In the box frame each box is
        jittered (``box_jitter``: per-axis size factor in ``[1 - j/2, 1 + j]``, centre shift
        ``N(0, j/3)`` box units) when ``augment`` is on: labelled and detected boxes do not
        fit their cars exactly."""
        clouds = [data.clouds[i] for i in pick]
        origins = data.origins[pick]
        if cfg.get("frame", "box") == "box":
            aspects = data.aspects[pick] if data.aspects is not None else np.tile(DEFAULT_ASPECT, (len(pick), 1))
            shift = np.zeros((len(pick), 3))
            if self.augment and self.box_jitter > 0:
                aspects = aspects * rng.uniform(1 - self.box_jitter / 2, 1 + self.box_jitter, (len(pick), 3))
                shift = rng.normal(0.0, self.box_jitter / 3, (len(pick), 3)) * aspects
            clouds = [to_box_frame(c - t, a) for c, t, a in zip(clouds, shift, aspects)]
            origins = to_box_frame(origins - shift, aspects)
        occupied, free = observation_grids(clouds, origins, grid_of(cfg), stop=float(cfg["stop"]),
                                           max_rays=int(cfg["max_rays"]))
        return ObservationBatch(torch.from_numpy(occupied), torch.from_numpy(free))

    # ---- losses

    def loss(self, net: nn.Module, batch: Any) -> tuple[torch.Tensor, dict[str, float]]:
        cfg = PRESETS[self.size]
        if self.stage == "prior":
            return vae_loss(net, batch, float(cfg["log_var"]), float(cfg["truncation"]), self.beta)
        lam = self.completer.lam if self.completer is not None else 1.0
        z, decoded = net(batch.grids())
        nll = observed_nll(decoded, batch.occupied, batch.free, float(cfg["log_var"]))
        prior = 0.5 * (z**2).sum(1)
        observed = (batch.occupied | batch.free).flatten(1).sum(1).clamp(min=1).float()
        loss = (nll + lam * prior).mean() / observed.mean()
        return loss, {"loss": float(loss.detach()), "nll_per_voxel": float((nll / observed).mean().detach()),
                      "z_norm": float(z.detach().norm(dim=1).mean())}

    # ---- validation and lambda selection (hooks of pcc_ros.train)

    def validation_data(self, source: Any, split: str, count: int, seed: int) -> tuple[Any, str]:
        if self.stage == "prior":
            val = _hash_split(source.keys, 0.1)
            return source.subset(np.flatnonzero(val)), "held-out reference shapes"

        return TrainingKit.require(self.kit, "aml").validation_instances(source, split, count, seed)

    def validate(self, completer: AML, val_data: Any, seed: int) -> dict[str, float]:
        if self.stage == "prior":
            return validate_prior(completer, val_data, self.beta)

        return TrainingKit.require(self.kit, "aml").validate(completer, val_data, seed)

    def prepare(self, completer: AML, data: Any, val_data: Any, seed: int) -> None:
        """Encoder stage: choose lambda with the ML baseline on validation instances."""
        if self.stage != "encoder":
            return
        if self.fixed_lam is not None:
            completer.lam = float(self.fixed_lam)
            self.lambda_sweep = {"chosen": completer.lam, "how": "given (--option lam)"}
            return
        real = None
        if self.real and self.lambda_real_weight > 0:
            open_cache = TrainingKit.require(self.kit, "aml").open_cache
            real = real_crops([open_cache(p) for p in self.real], "all")
        self.lambda_sweep = select_lambda(completer, val_data[: self.lambda_instances], self.lambdas,
                                          self.lambda_steps, seed, real=real, real_weight=self.lambda_real_weight,
                                          holdout=self.lambda_holdout)
        completer.lam = float(self.lambda_sweep["chosen"])
        log.info("aml: lambda %.3g chosen on %d validation instances: %s", completer.lam,
                 self.lambda_sweep["instances"], self.lambda_sweep["table"])

    def finalize(self, completer: AML, data: Any) -> None:
        """Prior stage, before the final save: whiten the latent space (:func:`whiten_latent`)."""
        if self.stage == "prior":
            self.whitening = whiten_latent(completer.model, data, float(completer.config["truncation"]))
            log.info("aml: latent whitened on %d reference shapes: %s", len(data), self.whitening)

    def summary(self) -> dict[str, Any]:
        """Extra facts for the checkpoint (the lambda sweep, the latent whitening)."""
        out: dict[str, Any] = {}
        if self.lambda_sweep:
            out["lambda_selection"] = self.lambda_sweep
        if getattr(self, "whitening", None):
            out["latent_whitening"] = self.whitening
        return out


@torch.no_grad()
def whiten_latent(net: AMLNet, reference: ReferenceSet, truncation: float, chunk: int = 32) -> dict[str, Any]:
    """Make ``N(0, I)`` the Gaussian fit of the reference shapes' codes, folded into the weights.

    A VAE whose KL term is small next to a likelihood summed over 31k voxels encodes its
    shapes far from ``N(0, I)`` (offset means, posterior sigma ~0.03), so ``z = 0`` and the
    ``||z||^2`` prior of Eq. 4/5 would not describe them. With ``m`` and ``C = L L^T`` the mean
    and covariance of the posterior means of the reference shapes, the decoder's first layer
    becomes ``W (m + L z') + b`` and the recognition model's mean ``L^-1 (mu - m)``: the same
    functions in the new coordinates ``z'``, where the reference codes are zero-mean and
    white. (The aggregate-posterior prior of two-stage VAEs, fitted as one Gaussian.)
    """
    was = net.training
    net.eval()
    q = net.latent
    mus = []
    for s in range(0, len(reference), chunk):
        occ = torch.from_numpy(reference.occupancy[s:s + chunk].astype(np.float32))
        sdf = torch.from_numpy(reference.sdf[s:s + chunk])
        x = torch.stack([occ, sdf / truncation], 1).contiguous(memory_format=torch.channels_last_3d)
        mus.append(net.prior_encoder(x.to(next(net.parameters()).device))[:, :q].double().cpu())
    mu = torch.cat(mus)
    mean = mu.mean(0)
    cov = torch.cov(mu.T) + 1e-6 * torch.eye(q, dtype=torch.float64)
    chol = torch.linalg.cholesky(cov)
    inv = torch.linalg.inv(chol)
    fc = net.decoder.fc
    w, b = fc.weight.double(), fc.bias.double()
    fc.bias.copy_((w @ mean + b).float())
    fc.weight.copy_((w @ chol).float())
    head = net.prior_encoder.fc
    wm, bm = head.weight[:q].double(), head.bias[:q].double()
    head.weight[:q] = (inv @ wm).float()
    head.bias[:q] = (inv @ (bm - mean)).float()
    net.train(was)
    return {"shapes": len(mu), "code_mean_norm": float(mean.norm()),
            "code_std": [round(float(v), 4) for v in cov.diagonal().sqrt()]}


def vae_loss(net: nn.Module, batch: PriorBatch, log_var: float, truncation: float, beta: float
             ) -> tuple[torch.Tensor, dict[str, float]]:
    """Eq. 3: ``-E_q[ln p(y|z)] + KL(q(z|y) || N(0, I))``, one sample, per voxel for the log."""
    grids = torch.stack([batch.occupancy, batch.sdf / truncation], 1).contiguous(memory_format=torch.channels_last_3d)
    mu, logvar, decoded = net(grids, prior=True)
    nll = reference_nll(decoded, batch.occupancy, batch.sdf, log_var)
    kl = 0.5 * (mu**2 + logvar.exp() - 1 - logvar).sum(1)
    voxels = float(np.prod(AML_GRID.resolution))
    loss = (nll + beta * kl).mean() / voxels
    return loss, {"loss": float(loss.detach()), "nll": float(nll.mean().detach()) / voxels,
                  "kl": float(kl.mean().detach())}


def validate_prior(completer: AML, val: ReferenceSet, beta: float, chunk: int = 32) -> dict[str, float]:
    """Held-out reference shapes: VAE loss (posterior mean), occupancy IoU and SDF sign IoU."""
    net = completer.model
    was = net.training
    net.eval()
    cfg = completer.config
    losses, ious, sdf_ious = [], [], []
    try:
        with torch.inference_mode():
            for s in range(0, len(val), chunk):
                occ = torch.from_numpy(val.occupancy[s:s + chunk].astype(np.float32)).to(completer.device)
                sdf = torch.from_numpy(val.sdf[s:s + chunk]).to(completer.device)
                loss, _ = vae_loss(net, PriorBatch(occ, sdf), float(cfg["log_var"]),
                                   float(cfg["truncation"]), beta)
                losses.append(float(loss) * len(occ))
                x = torch.stack([occ, sdf / float(cfg["truncation"])], 1)
                mu, _ = net.prior_encoder(x).chunk(2, dim=1)
                dec = net.decoder(mu)
                pred, truth = dec[:, 0] > 0, occ > 0.5
                ious.extend((pred & truth).flatten(1).sum(1).float().div(
                    (pred | truth).flatten(1).sum(1).clamp(min=1).float()).tolist())
                sp, st = dec[:, 1] < 0, sdf < 0
                sdf_ious.extend((sp & st).flatten(1).sum(1).float().div(
                    (sp | st).flatten(1).sum(1).clamp(min=1).float()).tolist())
    finally:
        net.train(was)
    return {"val_loss": float(np.sum(losses) / max(len(val), 1)), "val_iou": float(np.mean(ious)),
            "val_sdf_iou": float(np.mean(sdf_ious)), "val_instances": len(val)}


@dataclass
class RealCrops:
    """Real crops for lambda validation: canonical clouds, canonical sensor origins, box sizes (m)."""

    clouds: list[np.ndarray]
    origins: np.ndarray
    sizes: np.ndarray

    def __len__(self) -> int:
        return len(self.clouds)


def real_crops(caches: Sequence[Any], split: str = "all", min_points: int = 10) -> RealCrops:
    """The crops of real instance caches, already open (``split``: one split or ``all``)."""
    clouds, origins, sizes = [], [], []
    for cache in caches:  # a handful of caches
        splits = ("train", "val", "test") if split == "all" else (split,)
        idx = np.concatenate([cache.indices(s, min_points=min_points) for s in splits]).astype(np.int64)
        clouds.extend(np.asarray(cache.points(int(i)), np.float32) for i in idx)
        origins.append(cache.meta["origin"][idx].astype(np.float64).reshape(-1, 3))
        sizes.append(cache.meta["box_size"][idx].astype(np.float64).reshape(-1, 3))
    return RealCrops(clouds, np.concatenate(origins) if origins else np.zeros((0, 3)),
                     np.concatenate(sizes) if sizes else np.zeros((0, 3)))


def _ml_completions(completer: AML, grids: torch.Tensor, clouds: Sequence[np.ndarray], aspects: np.ndarray,
                    steps: int, lam: float) -> list[np.ndarray]:
    """The ML baseline's (Eq. 4) completions of observation ``grids`` with prior weight ``lam``,
    fitted and decoded in chunks of 32 (what lambda selection scores, on either domain)."""
    outs: list[np.ndarray] = []
    for s in range(0, len(clouds), 32):
        z = completer.fit_latent(grids[s:s + 32, 0] > 0.5, grids[s:s + 32, 1] > 0.5, steps=steps, lam=lam)
        with torch.inference_mode():
            outs.extend(completer.decode_points(completer.model.decoder(z), clouds[s:s + 32], aspects[s:s + 32]))
    return outs


def holdout_fidelity(completer: AML, crops: RealCrops, lambdas: Sequence[float], steps: int, holdout: float,
                     seed: int, repeats: int = 3) -> dict[str, float]:
    """Per lambda: the ML baseline fitted to a seeded ``1 - holdout`` share of each real crop's
    points; score = mean distance (metres) of the held-out points to the completion.

    A real crop has no complete ground truth; its own unseen points are the honest check of
    how well a completion explains the car (too strong a prior misses them; the likelihood
    is what fits them). ``repeats`` seeded splits per crop."""
    kept, held, origins, aspects, lengths = [], [], [], [], []
    for r in range(repeats):
        for i, cloud in enumerate(crops.clouds):  # a few dozen crops: index bookkeeping only
            rng = np.random.default_rng([seed, r, i])
            mask = rng.random(len(cloud)) < holdout
            if mask.all() or not mask.any():
                mask[: max(1, len(cloud) // 3)] = True
                mask[-1] = False
            kept.append(cloud[~mask])
            held.append(cloud[mask])
            origins.append(crops.origins[i])
            aspects.append(box_aspect(crops.sizes[i]) if completer.config.get("frame") == "box" else np.ones(3))
            lengths.append(crops.sizes[i, 0])
    origins, aspects = np.asarray(origins), np.asarray(aspects)
    with torch.inference_mode():
        x = torch.cat([completer.observe_frame(kept[s:s + 32], origins[s:s + 32], aspects[s:s + 32])
                       for s in range(0, len(kept), 32)])
    table = {}
    for lam in lambdas:  # a handful of candidates
        outs = _ml_completions(completer, x, kept, aspects, steps, lam)
        dist = [float(cKDTree(o).query(h)[0].mean()) * length for o, h, length in zip(outs, held, lengths)]
        table[str(lam)] = float(np.mean(dist))
    return table


def select_lambda(completer: AML, instances: Sequence[Any], lambdas: Sequence[float], steps: int, seed: int,
                  real: RealCrops | None = None, real_weight: float = 0.5, holdout: float = 0.3
                  ) -> dict[str, Any]:
    """Run the ML baseline (Eq. 4) with each lambda on validation data; the lowest score wins.

    Synthetic: CD-L1 (canonical) against the true shapes of SynthCars ``val`` instances. Real
    (when ``real`` crops are given): :func:`holdout_fidelity` in metres. Score of a lambda:
    ``(1 - w) * cd / min(cd) + w * real / min(real)`` with ``w = real_weight`` (each domain
    relative to its best candidate, so neither's units dominate)."""
    if not instances:
        raise ConfigError("aml: lambda selection needs validation instances (--val-instances > 0)")
    if not lambdas:
        raise ConfigError("aml: --option lambdas is empty")
    table = {}
    clouds = [inst.partial for inst in instances]
    contexts = [getattr(inst, "context", None) for inst in instances]  # attached by pcc_ros.evaluate
    with torch.inference_mode():
        observed = [completer.observe(clouds[s:s + 32], contexts[s:s + 32]) for s in range(0, len(clouds), 32)]
    x = torch.cat([o[0] for o in observed])
    aspects = np.concatenate([o[1] for o in observed])
    for lam in lambdas:  # a handful of candidates
        outs = _ml_completions(completer, x, clouds, aspects, steps, lam)
        cd = [instance_metrics(o, inst.reference, None, length=inst.length, with_emd=False)["cd_l1"]
              for o, inst in zip(outs, instances)]
        table[str(lam)] = float(np.mean(cd))
    out: dict[str, Any] = {"table": table, "metric": "val cd_l1 (canonical) of the ML baseline",
                           "instances": len(instances), "steps": steps, "seed": seed}
    score = {k: v / min(table.values()) for k, v in table.items()}
    if real is not None and len(real):
        real_table = holdout_fidelity(completer, real, lambdas, steps, holdout, seed)
        best = min(real_table.values())
        score = {k: (1 - real_weight) * score[k] + real_weight * real_table[k] / best for k in table}
        out.update({"real_table": real_table, "real_crops": len(real), "real_weight": real_weight,
                    "real_metric": f"held-out real points -> ML completion, metres ({holdout:.0%} of each "
                                   "crop's points held out, 3 seeded splits)", "score": score})
    out["chosen"] = float(min(score, key=score.get))
    return out


@AML.trains_with
def training_recipe(size: str = "default", **options: Any) -> AMLRecipe:
    """The training recipe ``pcc train aml`` uses (see :mod:`pcc_ros.train`)."""
    return AMLRecipe(size=size, **options)
