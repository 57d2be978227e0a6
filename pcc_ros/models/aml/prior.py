"""The shape prior's training data and checks: voxelised SynthCars reference shapes, grid
augmentation, the VAE loss (Eq. 3), validation and the latent whitening applied before saving."""

from __future__ import annotations

import json
import logging
import zlib
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn
from tqdm import tqdm

from pcc_ros.errors import DataError
from pcc_ros.geometry.voxels import AML_GRID, GridSpec, reference_grids, to_box_frame
from pcc_ros.models.aml.completer import AML
from pcc_ros.models.aml.likelihood import reference_nll
from pcc_ros.models.aml.network import GRIDS, AMLNet

log = logging.getLogger(__name__)


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


def hash_split(keys: Sequence[str], val_fraction: float) -> np.ndarray:
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
    # the fit runs on the CPU in float64; the weights it folds into may live on a GPU
    mean, chol, inv = (t.to(fc.weight.device) for t in (mean, chol, inv))
    w, b = fc.weight.double(), fc.bias.double()
    fc.bias.copy_((w @ mean + b).float())
    fc.weight.copy_((w @ chol).float())
    head = net.prior_encoder.fc
    wm, bm = head.weight[:q].double(), head.bias[:q].double()
    head.weight[:q] = (inv @ wm).float()
    head.bias[:q] = (inv @ (bm - mean)).float()
    net.train(was)
    return {"shapes": len(mu), "code_mean_norm": float(mean.norm().cpu()),
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
