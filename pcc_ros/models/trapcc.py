"""TraPCC: self-supervised completion from real-scan pseudo ground truth, with a scene graph.

Paper: ``shared/papers/trapcc.txt`` §4. No complete shape is ever used for training: the
supervision is the Whole-GT / Partial-GT pools of aggregated real tracks
(:mod:`pcc_ros.data.gt_pools`), retrieved per instance by size then MCD.

Network (all on packed batches, see :mod:`pcc_ros.models.layers`):

* **P-Net** — the canonical input is split by the box into front (x >= 0) and back
  (x < 0). Each half that holds points is encoded by a PCN encoder (two PointNet stages,
  shared by both halves) and decoded by a fully connected decoder conditioned on which half
  it is into ``half_points`` points of that half (no coarse-to-fine folding: the paper
  drops it because real pseudo-GT is not dense). A missing half gives no partial
  prediction. The present halves stitched together are the *coarse* object.
* **C-Net** — a second PCN encoder over the input and the coarse points together, plus
  the P-Net half features, gives the global code, decoded by a folding decoder
  (FC to ``coarse_points``, one 2x2 folding step) into the *detailed* whole.
* **Scene graph** — the ``k`` (3) nearest other vehicles of the frame within ``radius``
  metres (:meth:`SceneContext.nearest`, box-centre distance) are encoded by a small PCN
  encoder; their features, concatenated with their geometry relative to the target
  (:func:`neighbour_geometry`: centre in the target's canonical frame, relative yaw,
  distance, and whether the neighbour lies between the target and the sensor), are
  aggregated into the C-Net code by ``scene_graph``:

  - ``attention`` (default): single-head attention with the target code as query over the
    neighbours plus a learned *null* slot, added through a zero-initialised projection.
    Why: the number of neighbours varies (0-3), their relevance differs (an occluder
    between target and sensor explains a missing part; a car behind it does not) and the
    null slot lets the network ignore irrelevant neighbours, so an isolated car is
    completed exactly as by CP-Net;
  - ``mean``: plain graph aggregation (mean of the neighbour messages), the alternative;
  - ``none``: CP-Net (the ablation without the scene graph).

  ``pnet=False`` is the C-Net-alone ablation (C-Net encodes the input directly).

The training recipe (pseudo-GT pools, batches, the loss) is :mod:`pcc_ros.models.trapcc_recipe`,
attached to the backend on import.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import nn

from pcc_ros.errors import ConfigError
from pcc_ros.geometry.canonical import to_canonical
from pcc_ros.models.base import (
    SceneContext,
    TorchCompleter,
    resample_cloud,
)
from pcc_ros.models.layers import FoldingDecoder, PCNEncoder, SharedMLP
from pcc_ros.models.registry import register

log = logging.getLogger(__name__)

NUM_HALVES = 2  # 0 = front (x >= 0), 1 = back
GEOMETRY_FEATURES = 7
SCENE_GRAPHS = ("attention", "mean", "none")

PRESETS: dict[str, dict[str, Any]] = {
    "default": {
        "max_input_points": 512,
        "half_encoder_widths1": [32, 64],
        "half_encoder_widths2": [128, 256],
        "half_decoder_widths": [256],
        "half_points": 128,
        "encoder_widths1": [64, 128],
        "encoder_widths2": [128, 256],
        "decoder_fc_widths": [256, 256],
        "coarse_points": 512,
        "grid_size": 2,
        "fold_widths": [64, 64],
        "grid_scale": 0.02,
        "neighbour_encoder_widths1": [32, 64],
        "neighbour_encoder_widths2": [64, 128],
        "neighbour_points": 256,
        "attention_dim": 64,
        "scene_graph": "attention",
        "pnet": True,
        "k_neighbours": 3,
        "radius": 20.0,
    },
}


def neighbour_geometry(center: np.ndarray, yaw: float, length: float, nb_center: np.ndarray, nb_yaw: np.ndarray,
                       radius: float, sensor_origin: np.ndarray | None = None) -> np.ndarray:
    """``(K, 7)`` features of neighbours relative to a target box (the scene-graph edges).

    Columns: neighbour centre in the target's canonical frame divided by ``radius / length``
    (3), ``sin`` / ``cos`` of the relative yaw (2), centre distance / ``radius`` (1), and the
    cosine between target->neighbour and target->sensor (1: the neighbour is between the
    target and the sensor, the external-occlusion case of TraPCC §4.3).
    """
    nb_center = np.asarray(nb_center, dtype=np.float64).reshape(-1, 3)
    if len(nb_center) == 0:
        return np.zeros((0, GEOMETRY_FEATURES), np.float32)
    origin = np.zeros(3) if sensor_origin is None else np.asarray(sensor_origin, dtype=np.float64).reshape(3)
    rel = to_canonical(nb_center, center, yaw, length)
    sensor = to_canonical(origin[None], center, yaw, length)[0]
    dyaw = np.asarray(nb_yaw, dtype=np.float64) - yaw
    dist = np.linalg.norm(rel, axis=1)
    towards = rel @ sensor / np.maximum(dist * np.linalg.norm(sensor), 1e-9)
    feats = np.concatenate(
        [rel / (radius / length), np.sin(dyaw)[:, None], np.cos(dyaw)[:, None], (dist * length / radius)[:, None],
         towards[:, None]], axis=1)
    return feats.astype(np.float32)


def nearest_neighbours(centers: np.ndarray, k: int, radius: float) -> np.ndarray:
    """``(n, k)`` indices of each box's ``k`` nearest other boxes within ``radius`` (-1 pads).

    Same rule as :meth:`SceneContext.nearest` (box-centre distance, stable order).
    """
    c = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    n = len(c)
    out = np.full((n, k), -1, dtype=np.int64)
    if n < 2 or k < 1:
        return out
    d = np.linalg.norm(c[:, None] - c[None], axis=2)
    np.fill_diagonal(d, np.inf)
    order = np.argsort(d, axis=1, kind="stable")[:, :k]
    ok = np.take_along_axis(d, order, axis=1) <= radius
    m = order.shape[1]
    out[:, :m] = np.where(ok, order, -1)
    return out


# --------------------------------------------------------------------------- network


@dataclass
class NeighbourBatch:
    """Packed neighbours: ``K`` slots per target."""

    points: torch.Tensor  # (P, 3)
    segment: torch.Tensor  # (P,) in [0, B*K), sorted
    mask: torch.Tensor  # (B, K) slot holds a neighbour
    geometry: torch.Tensor  # (B, K, 7)

    def to(self, device: torch.device) -> NeighbourBatch:
        return NeighbourBatch(*(t.to(device, non_blocking=True) for t in (self.points, self.segment, self.mask,
                                                                            self.geometry)))


def pack_neighbours(clouds: Sequence[Sequence[np.ndarray]], geometry: Sequence[np.ndarray], k: int) -> NeighbourBatch:
    """Neighbour clouds (``clouds[b]`` up to ``k`` each) and their geometry into a batch."""
    b = len(clouds)
    mask = np.zeros((b, k), dtype=bool)
    geo = np.zeros((b, k, GEOMETRY_FEATURES), dtype=np.float32)
    pts, seg = [], []
    for i, (nbs, g) in enumerate(zip(clouds, geometry)):  # targets x <= k neighbours
        for j, c in enumerate(nbs[:k]):
            mask[i, j] = True
            geo[i, j] = g[j]
            pts.append(c)
            seg.append(np.full(len(c), i * k + j, dtype=np.int64))
    points = np.concatenate(pts).astype(np.float32) if pts else np.zeros((0, 3), np.float32)
    segment = np.concatenate(seg) if seg else np.zeros(0, np.int64)
    return NeighbourBatch(torch.from_numpy(np.ascontiguousarray(points)), torch.from_numpy(segment),
                          torch.from_numpy(mask), torch.from_numpy(geo))


class TraPCCNet(nn.Module):
    """P-Net + C-Net + scene graph on packed batches."""

    def __init__(self, cfg: dict[str, Any]) -> None:
        super().__init__()
        self.use_pnet = bool(cfg["pnet"])
        self.scene_graph = str(cfg["scene_graph"])
        self.k = int(cfg["k_neighbours"])
        if self.use_pnet:
            self.half_encoder = PCNEncoder(cfg["half_encoder_widths1"], cfg["half_encoder_widths2"])
            hd = self.half_encoder.out_dim
            self.half_points = int(cfg["half_points"])
            self.half_decoder = SharedMLP(hd + NUM_HALVES, [*cfg["half_decoder_widths"], self.half_points * 3])
            self.register_buffer("one_hot", torch.eye(NUM_HALVES), persistent=False)
        self.encoder = PCNEncoder(cfg["encoder_widths1"], cfg["encoder_widths2"])
        code = self.encoder.out_dim
        self.code_dim = code
        if self.use_pnet:
            self.half_proj = nn.Linear(self.half_encoder.out_dim, code)
        if self.scene_graph != "none":
            self.nb_encoder = PCNEncoder(cfg["neighbour_encoder_widths1"], cfg["neighbour_encoder_widths2"])
            a = int(cfg["attention_dim"])
            self.nb_message = SharedMLP(self.nb_encoder.out_dim + GEOMETRY_FEATURES, [a, a])
            if self.scene_graph == "attention":
                self.query = nn.Linear(code, a)
                self.key = nn.Linear(a, a)
                self.null_key = nn.Parameter(torch.zeros(a))
            self.scene_out = nn.Linear(a, code)
            nn.init.zeros_(self.scene_out.weight)
            nn.init.zeros_(self.scene_out.bias)
        self.decoder = FoldingDecoder(code, cfg["decoder_fc_widths"], int(cfg["coarse_points"]),
                                      int(cfg["grid_size"]), cfg["fold_widths"], float(cfg["grid_scale"]))

    @property
    def num_output_points(self) -> int:
        return self.decoder.num_points

    def scene(self, code: torch.Tensor, nb: NeighbourBatch) -> torch.Tensor:
        """Scene-graph message added to the C-Net code (zero when a target has no neighbour)."""
        b, k = nb.mask.shape
        e = self.nb_encoder(nb.points, nb.segment, b * k).view(b, k, -1)
        msg = self.nb_message(torch.cat([e, nb.geometry], dim=2))  # (B, K, A)
        maskf = nb.mask.to(msg.dtype)
        if self.scene_graph == "mean":
            agg = (msg * maskf[..., None]).sum(1) / maskf.sum(1, keepdim=True).clamp_min(1.0)
        else:
            q = self.query(code)  # (B, A)
            keys = self.key(msg)  # (B, K, A)
            logits = (keys * q[:, None, :]).sum(-1) / keys.shape[-1] ** 0.5
            logits = logits.masked_fill(~nb.mask, float("-inf"))
            null = (q * self.null_key).sum(-1, keepdim=True) / keys.shape[-1] ** 0.5
            weights = torch.softmax(torch.cat([null, logits], dim=1), dim=1)[:, 1:]
            agg = (weights[..., None] * msg).sum(1)
        return self.scene_out(torch.relu(agg))

    def forward(self, points: torch.Tensor, segment: torch.Tensor, batch_size: int,
                neighbours: NeighbourBatch | None = None) -> dict[str, torch.Tensor]:
        """Complete a packed batch.

        Returns ``detailed (B, M, 3)``; with P-Net also ``coarse (B, 2, H, 3)`` (rows of absent
        halves are meaningless and masked by) ``present (B, 2)``.
        """
        b = batch_size
        out: dict[str, torch.Tensor] = {}
        enc_points, enc_segment = points, segment
        half_code = None
        if self.use_pnet:
            half = (points[:, 0] < 0).long()  # 0 = front, 1 = back
            hseg = segment * NUM_HALVES + half
            order = torch.argsort(hseg, stable=True)
            e_h = self.half_encoder(points[order], hseg[order], b * NUM_HALVES)  # (2B, C)
            present = (torch.bincount(hseg, minlength=b * NUM_HALVES) > 0).view(b, NUM_HALVES)
            code_h = torch.cat([e_h, self.one_hot.repeat(b, 1)], dim=1)
            coarse = self.half_decoder(code_h).view(b, NUM_HALVES, self.half_points, 3)
            out["coarse"], out["present"] = coarse, present
            # stitch the present halves and feed them to C-Net with the input
            rows = present.view(-1).nonzero(as_tuple=True)[0]
            stitched = coarse.view(b * NUM_HALVES, self.half_points, 3)[rows].reshape(-1, 3)
            st_seg = (rows // NUM_HALVES).repeat_interleave(self.half_points)
            all_seg = torch.cat([segment, st_seg])
            order = torch.argsort(all_seg, stable=True)
            enc_points, enc_segment = torch.cat([points, stitched])[order], all_seg[order]
            pooled = e_h.view(b, NUM_HALVES, -1).masked_fill(~present[..., None], float("-inf")).amax(1)
            half_code = self.half_proj(pooled)
        code = self.encoder(enc_points, enc_segment, b)
        if half_code is not None:
            code = code + half_code
        if self.scene_graph != "none" and neighbours is not None and bool(neighbours.mask.any()):
            code = code + self.scene(code, neighbours)
        _, detailed = self.decoder(code)
        out["detailed"] = detailed
        return out


def pack_inputs(clouds: Sequence[np.ndarray]) -> tuple[torch.Tensor, torch.Tensor]:
    lengths = np.fromiter((len(c) for c in clouds), dtype=np.int64, count=len(clouds))
    points = np.concatenate(clouds).astype(np.float32, copy=False) if len(clouds) else np.zeros((0, 3), np.float32)
    return (torch.from_numpy(np.ascontiguousarray(points)),
            torch.from_numpy(np.repeat(np.arange(len(clouds), dtype=np.int64), lengths)))


# --------------------------------------------------------------------------- completer


@register("trapcc")
class TraPCC(TorchCompleter):
    """TraPCC completer: canonical partial clouds (+ scene contexts) in, ``M`` canonical points out."""

    uses_context = True

    #: The named sizes of the network.
    presets = PRESETS

    def build_model(self) -> TraPCCNet:
        if self.config["scene_graph"] not in SCENE_GRAPHS:
            raise ConfigError(f"trapcc: scene_graph must be one of {SCENE_GRAPHS}, got {self.config['scene_graph']!r}")
        for key in ("max_input_points", "neighbour_points", "k_neighbours", "half_points", "coarse_points"):
            if int(self.config[key]) < 1:
                raise ConfigError(f"trapcc: {key} must be >= 1, got {self.config[key]}")
        if not float(self.config["radius"]) > 0:
            raise ConfigError(f"trapcc: radius must be > 0 metres, got {self.config['radius']}")
        return TraPCCNet(self.config)

    @property
    def num_output_points(self) -> int:
        return self.model.num_output_points

    def prepare(self, clouds: Sequence[np.ndarray], cap: int | None = None) -> list[np.ndarray]:
        cap = int(cap or self.config["max_input_points"])
        return [c if len(c) <= cap else resample_cloud(c, cap) for c in clouds]

    def neighbours_of(self, contexts: Sequence[SceneContext | None]) -> NeighbourBatch | None:
        """The scene-graph neighbours of each target from its :class:`SceneContext`."""
        if self.config["scene_graph"] == "none" or all(c is None for c in contexts):
            return None
        k, radius = int(self.config["k_neighbours"]), float(self.config["radius"])
        clouds, geometry = [], []
        for ctx in contexts:  # loop over targets; each has <= k neighbours
            if ctx is None or len(ctx.neighbour_boxes) == 0:
                clouds.append([])
                geometry.append(np.zeros((0, GEOMETRY_FEATURES), np.float32))
                continue
            near = ctx.nearest(k, radius)
            box = near.box
            clouds.append(self.prepare([np.asarray(p, dtype=np.float32)[:, :3] for p in near.neighbour_points
                                        if len(p)], int(self.config["neighbour_points"])))
            keep = np.array([len(p) > 0 for p in near.neighbour_points], dtype=bool)
            geometry.append(neighbour_geometry(box.center[0], float(box.yaw[0]), float(box.size[0, 0]),
                                               near.neighbour_boxes.center[keep], near.neighbour_boxes.yaw[keep],
                                               radius, near.sensor_origin))
        return pack_neighbours(clouds, geometry, k)

    def forward_batch(self, clouds: list[np.ndarray], contexts: list[SceneContext | None]) -> list[np.ndarray]:
        points, segment = pack_inputs(self.prepare(clouds))
        nb = self.neighbours_of(contexts)
        if nb is not None:
            nb = nb.to(self.device)
            dtype = next(self.model.parameters()).dtype  # half_precision: the pre-hook casts only plain tensors
            nb = NeighbourBatch(nb.points.to(dtype), nb.segment, nb.mask, nb.geometry.to(dtype))
        out = self.model(points.to(self.device), segment.to(self.device), len(clouds), nb)
        return list(out["detailed"].float().cpu().numpy())


# The training recipe registers itself on TraPCC (``@TraPCC.trains_with``) when imported; it
# imports this module, so it comes last.
from pcc_ros.models import trapcc_recipe as trapcc_recipe  # noqa: E402
