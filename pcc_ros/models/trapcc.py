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

Loss (Eq. 3): ``CD(coarse, Partial-GT) + CD(detailed, Whole-GT) + MCD(input -> detailed)``.
The Chamfer terms are Chamfer-L1 (Euclidean, averaged both ways; PCN's form) and MCD is
the one-sided input -> detailed mean Euclidean distance. The paper writes squared
distances (Eq. 1, 2); with canonical units (~0.01-0.1) squares make the gradients of the
fine-detail errors vanish, so the training uses the L1 forms (documented in
``docs/trapcc.md``); the evaluation reports the paper's squared L-G / L-I / L-S.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from pcc_ros.errors import ConfigError, DataError
from pcc_ros.geometry.canonical import to_canonical
from pcc_ros.models.base import (
    CacheRecipe,
    CacheTrainOptions,
    SceneContext,
    TorchCompleter,
    TrainingKit,
    aspect_scales,
    cache_origin,
    resample_cloud,
)
from pcc_ros.models.layers import FoldingDecoder, PCNEncoder, SharedMLP, masked_mean, nearest, weighted_chamfer
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


# --------------------------------------------------------------------------- training


@dataclass
class TrainOptions(CacheTrainOptions):
    """Training options of TraPCC (stored in the checkpoint's ``training.recipe``; ``box_aspect``,
    ``held_out`` and ``input_points`` are :class:`~pcc_ros.models.base.CacheTrainOptions`'s: with
    ``box_aspect`` the pseudo-GT is scaled like the inputs, while neighbour clouds stay in their own
    canonical frames, as the pipeline's :class:`SceneContext` gives them; the held-out check covers
    the pool caches too)."""

    #: extra instance caches trained on together with ``--data`` (e.g. real KITTI / nuScenes)
    real_data: list[str] = field(default_factory=list)
    #: share of each batch drawn from ``real_data`` (oversampling the few real scans); 0: natural share
    real_share: float = 0.1
    #: where pools and retrievals are cached (default ``<--data>/trapcc_gt``)
    gt_dir: str | None = None
    whole_loss_points: int = 384
    half_loss_points: int = 256
    #: input points the MCD term compares (a random subset of the input when larger)
    input_loss_points: int = 256
    #: detailed points in the Whole-GT Chamfer term, a fresh random subset each step (0: all);
    #: halves the cost of the largest distance matrix, every point is still trained over steps
    detail_loss_points: int = 1024
    weight_partial: float = 1.0
    weight_whole: float = 1.0
    weight_input: float = 1.0
    #: random point dropout of training inputs (probability of thinning an input to 20-100 %)
    input_dropout: float = 0.5
    #: Chamfer form of the loss terms: "l1" (Euclidean) or "l2" (squared, the paper's Eq. 1-2)
    chamfer: str = "l1"
    min_points_pool: int = 1024
    size_candidates: int = 8
    #: instance caches the pseudo-GT pools are built from instead of the training caches, e.g. the
    #: tight crops of the same recordings when the training inputs are cropped as the node crops
    #: (``pcc extract --node-crop``): inputs look like the node's, targets stay the car itself
    pool_data: list[str] = field(default_factory=list)


@dataclass
class TrainData:
    """Everything the sampler needs, built once from the caches (partial scans only)."""

    clouds: list[np.ndarray]  # every training observation (canonical)
    whole: np.ndarray  # (N,) Whole-GT pool index (>= 0)
    front: np.ndarray  # (N,) front Partial-GT index or -1
    back: np.ndarray  # (N,) back Partial-GT index or -1
    neighbours: np.ndarray  # (N, K) indices into ``nb_clouds`` or -1
    geometry: np.ndarray  # (N, K, 7)
    nb_clouds: list[np.ndarray]  # every observation of the caches (neighbours may be any split)
    real: np.ndarray  # (N,) bool: from a real-data cache
    pools: Any
    summary: dict[str, Any]

    def __len__(self) -> int:
        return len(self.clouds)

    def __iter__(self) -> Iterator[tuple[np.ndarray]]:
        """One single-observation group per instance (what ``pcc train`` counts as observations)."""
        return ((c,) for c in self.clouds)


@dataclass
class TrainBatch:
    points: torch.Tensor
    segment: torch.Tensor
    batch_size: int
    neighbours: NeighbourBatch | None
    inputs: torch.Tensor  # (B, N, 3) padded input (MCD target)
    input_mask: torch.Tensor
    whole: torch.Tensor  # (B, W, 3)
    whole_mask: torch.Tensor
    half: torch.Tensor  # (B, 2, H, 3)
    half_mask: torch.Tensor  # (B, 2, H)

    def to(self, device: torch.device) -> TrainBatch:
        t = [x.to(device, non_blocking=True) for x in (self.points, self.segment)]
        rest = [x.to(device, non_blocking=True) for x in (self.inputs, self.input_mask, self.whole, self.whole_mask,
                                                          self.half, self.half_mask)]
        return TrainBatch(*t, self.batch_size, None if self.neighbours is None else self.neighbours.to(device), *rest)


class TraPCCRecipe(CacheRecipe):
    """What ``pcc train trapcc`` needs (see :mod:`pcc_ros.train`)."""

    name = "trapcc"
    default_lr = 5e-4

    def __init__(self, size: str = "default", options: TrainOptions | None = None, **model: Any) -> None:
        super().__init__(size, options or TrainOptions())
        if self.options.chamfer not in ("l1", "l2"):
            raise ConfigError(f"trapcc: chamfer must be l1 or l2, got {self.options.chamfer!r}")
        if not 0.0 <= self.options.real_share <= 1.0:
            raise ConfigError(f"trapcc: real_share must be in [0, 1], got {self.options.real_share}")
        self.model = model
        self.data_summary_: dict[str, Any] = {}

    def use_real_data(self, caches: list[str], share: float) -> None:
        """``pcc train --real-data CACHE --real-share S``: the same as ``--option real_data=[...]``."""
        if not 0.0 <= share <= 1.0:
            raise ConfigError(f"trapcc: real_share must be in [0, 1], got {share}")
        self.options.real_data = [*self.options.real_data, *caches]
        self.options.real_share = float(share)

    def mix_real_data(self, data: TrainData, min_points: int) -> tuple[TrainData, dict[str, Any]]:
        """The real caches are already in ``data`` (and in the pools): :meth:`training_data` mixed them
        at ``real_share`` of the samples; what it mixed is the data summary."""
        return data, self.data_summary()

    def build_completer(self, device: str) -> TraPCC:
        return TraPCC(device=device, size=self.size, **self.model)

    def settings(self) -> dict[str, Any]:
        return dict(self.model)

    def data_summary(self) -> dict[str, Any]:
        return dict(self.data_summary_)

    # ---- data

    def training_data(self, cache: Any, split: str, min_points: int = 10) -> TrainData:
        """Training observations of ``cache`` (and ``real_data`` caches) with their pseudo-GT.

        Pools are built from the ``split`` tracks of all caches together; retrieval is cached
        (see :mod:`pcc_ros.data.gt_pools`). Instances without a Whole-GT (empty pool) are left out.
        """
        kit = TrainingKit.require(self.kit, "trapcc")
        caches = [cache, *(self._open(kit, path, "real_data") for path in self.options.real_data)]
        pool_caches = [self._open(kit, path, "pool_data") for path in self.options.pool_data] or caches
        held_out = self.check_held_out([*caches, *pool_caches])
        pool_cfg = kit.pool_config(min_points=int(self.options.min_points_pool),
                              min_half_points=int(self.options.min_points_pool) // 2,
                              size_candidates=int(self.options.size_candidates))
        root = Path(self.options.gt_dir) if self.options.gt_dir else Path(cache.root) / "trapcc_gt"
        pools, folder = kit.load_or_build_pools(pool_caches, split, root, pool_cfg)
        if len(pools.whole) == 0:
            raise ConfigError(f"trapcc: the Whole-GT pool of split {split!r} is empty (no track aggregate passed "
                              f"the >= {pool_cfg.min_points} points + evenness test); add tracked data")
        cfg = {**PRESETS[self.size], **self.model}
        k, radius = int(cfg["k_neighbours"]), float(cfg["radius"])
        if self.options.box_aspect:  # the main training data fixes the reference
            self.fix_aspect(np.asarray(cache.meta["box_size"])[cache.indices(split, min_points=min_points)])
        clouds, nb_clouds, whole, front, back, real, nbs, geos = [], [], [], [], [], [], [], []
        per_source = []
        for s, c in enumerate(caches):
            idx = c.indices(split, min_points=min_points)
            a = kit.load_or_assign(pools, folder, c, idx, f"{split}-min{min_points}", pool_cfg.size_candidates)
            base = len(nb_clouds)
            all_idx = np.arange(len(c))
            nb_clouds.extend(np.asarray(c.points(int(i)), dtype=np.float32) for i in all_idx)
            nb_index = np.full((len(c), k), -1, dtype=np.int64)
            geo = np.zeros((len(c), k, GEOMETRY_FEATURES), np.float32)
            centers, yaws, sizes = c.meta["box_center"], c.meta["box_yaw"], c.meta["box_size"]
            for group in c.frame_groups():  # loop over frames (thousands), tens of boxes each
                near = nearest_neighbours(centers[group], k, radius)
                for row, i in enumerate(group):
                    ok = near[row] >= 0
                    j = group[near[row][ok]]
                    nb_index[i, : len(j)] = base + j
                    geo[i, : len(j)] = neighbour_geometry(centers[i], yaws[i], sizes[i, 0], centers[j], yaws[j], radius)
            usable = a["whole_index"] >= 0
            sel = idx[usable]
            if self.aspect is not None:  # inputs in the box-aspect frame; neighbours keep their own frame
                scales = aspect_scales(np.asarray(sizes)[sel], self.aspect, len(sel))
                clouds.extend(nb_clouds[base + int(i)] * sc for i, sc in zip(sel, scales))
            else:
                clouds.extend(nb_clouds[base + int(i)] for i in sel)
            whole.append(a["whole_index"][usable])
            front.append(a["front_index"][usable])
            back.append(a["back_index"][usable])
            nbs.append(nb_index[sel])
            geos.append(geo[sel])
            real.append(np.full(len(sel), s > 0))
            per_source.append({"cache": str(c.root), "instances": len(sel), "real": s > 0, **cache_origin(c)})
        gt = pools if self.aspect is None else aspect_pools(pools, self.aspect)
        data = TrainData(clouds, np.concatenate(whole), np.concatenate(front), np.concatenate(back),
                         np.concatenate(nbs), np.concatenate(geos), nb_clouds, np.concatenate(real), gt, {})
        n_real = int(data.real.sum())
        share = self.options.real_share if n_real and n_real < len(data) else n_real / max(len(data), 1)
        data.summary = {
            "sources": per_source, "instances": len(data), "real_instances": n_real,
            "real_fraction_of_instances": n_real / max(len(data), 1), "real_share_of_samples": share,
            "pools": {p: pools.stats.get(p) for p in ("whole", "front", "back")},
            "pool_folder": str(folder),
            "pool_sources": [{"cache": str(c.root), **cache_origin(c)} for c in pool_caches],
            "held_out": held_out, "box_aspect": self.aspect_record(),
            "complete_shapes_used": False,
        }
        self.data_summary_ = data.summary
        log.info("trapcc training data: %s", data.summary)
        return data

    @staticmethod
    def _open(kit: TrainingKit, path: str, option: str) -> Any:
        try:
            return kit.open_cache(Path(path))
        except DataError as exc:
            raise ConfigError(f"trapcc: {option} cache {path}: {exc}") from exc

    # ---- batches

    def make_batch(self, data: TrainData, chosen: np.ndarray, cfg: dict[str, Any],
                   rng: np.random.Generator) -> TrainBatch:
        o = self.options
        cap = min(int(cfg["max_input_points"]), int(o.input_points or cfg["max_input_points"]))
        inputs = []
        for i in chosen:  # instances of a batch (tens); per-point work vectorised
            c = data.clouds[int(i)]
            if len(c) > cap:
                c = c[rng.choice(len(c), cap, replace=False)]
            if len(c) > 8 and rng.random() < o.input_dropout:
                keep = max(4, int(len(c) * rng.uniform(0.2, 1.0)))
                c = c[rng.choice(len(c), keep, replace=False)]
            inputs.append(np.asarray(c, dtype=np.float32))
        b = len(chosen)
        targets = [c if len(c) <= o.input_loss_points else c[rng.choice(len(c), o.input_loss_points, replace=False)]
                   for c in inputs]
        n_in = max(len(c) for c in targets)
        inp = np.zeros((b, n_in, 3), np.float32)
        inp_mask = np.zeros((b, n_in), bool)
        for r, c in enumerate(targets):
            inp[r, : len(c)] = c
            inp_mask[r, : len(c)] = True
        whole, whole_mask = self._gt(data.pools.whole, data.whole[chosen], o.whole_loss_points, rng)
        hf, hf_mask = self._gt(data.pools.front, data.front[chosen], o.half_loss_points, rng)
        hb, hb_mask = self._gt(data.pools.back, data.back[chosen], o.half_loss_points, rng)
        neighbours = None
        if cfg["scene_graph"] != "none":
            k = int(cfg["k_neighbours"])
            nb_cap = int(cfg["neighbour_points"])
            nb_clouds, nb_geo = [], []
            for i in chosen:
                ids = data.neighbours[int(i)]
                cl = []
                for j in ids[ids >= 0]:
                    c = data.nb_clouds[int(j)]
                    cl.append(c if len(c) <= nb_cap else c[rng.choice(len(c), nb_cap, replace=False)])
                nb_clouds.append(cl)
                nb_geo.append(data.geometry[int(i)][: len(cl)])
            neighbours = pack_neighbours(nb_clouds, nb_geo, k)
        points, segment = pack_inputs(inputs)
        return TrainBatch(points, segment, b, neighbours, torch.from_numpy(inp), torch.from_numpy(inp_mask),
                          torch.from_numpy(whole), torch.from_numpy(whole_mask),
                          torch.from_numpy(np.stack([hf, hb], axis=1)),
                          torch.from_numpy(np.stack([hf_mask, hb_mask], axis=1)))

    @staticmethod
    def _gt(pool: Any, index: np.ndarray, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """``(B, n, 3)`` random subsets of the assigned pool entries; rows with index -1 masked out."""
        b = len(index)
        out = np.zeros((b, n, 3), np.float32)
        mask = np.zeros((b, n), bool)
        valid = np.flatnonzero(index >= 0)
        if len(valid) == 0 or len(pool) == 0:
            return out, mask
        counts = pool.count[index[valid]]
        pick = (rng.random((len(valid), n)) * counts[:, None]).astype(np.int64)
        out[valid] = pool.points[index[valid][:, None], pick]
        mask[valid] = True
        return out, mask

    def sampling_weights(self, data: TrainData) -> np.ndarray | None:
        """Per-instance sampling probabilities giving real data ``real_share`` of the samples
        (``None``: uniform, when there is no real data or only real data)."""
        n_real = int(data.real.sum())
        if not 0 < n_real < len(data):
            return None
        share = self.options.real_share
        weights = np.where(data.real, share / n_real, (1 - share) / (len(data) - n_real))
        return weights / weights.sum()

    def batches(self, data: TrainData, batch_size: int, cfg: dict[str, Any],
                rng: np.random.Generator) -> Iterator[TrainBatch]:
        if len(data) == 0:
            raise ConfigError("trapcc: no training instances")
        weights = self.sampling_weights(data)
        while True:
            chosen = rng.choice(len(data), batch_size, replace=len(data) < batch_size or weights is not None,
                                p=weights)
            yield self.make_batch(data, chosen, cfg, rng)

    # ---- loss

    def loss(self, net: nn.Module, batch: TrainBatch) -> tuple[torch.Tensor, dict[str, float]]:
        return trapcc_loss(net, batch, self.options)


def aspect_pools(pools: Any, aspect: Sequence[float]) -> Any:
    """The pseudo-GT pools in the box-aspect frame: each entry scaled by its own track's box
    (``Pool.size``), i.e. every target car fills the reference box as the scaled inputs do."""
    parts = {}
    for name in ("whole", "front", "back"):
        pool = pools.part(name)
        if len(pool):
            scales = aspect_scales(pool.size, aspect, len(pool))
            pool = dataclasses.replace(pool, points=(pool.points * scales[:, None, :]).astype(np.float32))
        parts[name] = pool
    return dataclasses.replace(pools, **parts)


def trapcc_loss(net: nn.Module, batch: TrainBatch, options: TrainOptions) -> tuple[torch.Tensor, dict[str, float]]:
    """TraPCC Eq. 3: ``CD(coarse, P-GT) + CD(detailed, W-GT) + MCD(input -> detailed)``."""
    out = net(batch.points, batch.segment, batch.batch_size, batch.neighbours)
    detailed = out["detailed"]
    squared = options.chamfer == "l2"
    sub = detailed
    if 0 < options.detail_loss_points < detailed.shape[1]:  # a fresh random subset every step
        pick = torch.randperm(detailed.shape[1], device=detailed.device)[: options.detail_loss_points]
        sub = detailed[:, pick]
    whole = chamfer(batch.whole, batch.whole_mask, sub, 0.5, squared)
    has_whole = batch.whole_mask.any(-1)
    l_whole = masked_mean(whole, has_whole)
    l_input = masked_mean(one_sided(batch.inputs, batch.input_mask, detailed, squared), batch.input_mask.any(-1))
    loss = options.weight_whole * l_whole + options.weight_input * l_input
    stats = {"whole": float(l_whole.detach()), "input": float(l_input.detach())}
    if "coarse" in out:
        part = chamfer(batch.half, batch.half_mask, out["coarse"], 0.5, squared)  # (B, 2)
        use = out["present"] & batch.half_mask.any(-1)
        l_part = masked_mean(part, use)
        loss = loss + options.weight_partial * l_part
        stats["partial"] = float(l_part.detach())
    stats["loss"] = float(loss.detach())
    return loss, stats


def one_sided(source: torch.Tensor, source_mask: torch.Tensor, pred: torch.Tensor, squared: bool = False
              ) -> torch.Tensor:
    """MCD (TraPCC Eq. 2): mean distance from each valid ``source`` point to its nearest ``pred`` point.

    One nearest-neighbour query (source -> prediction) instead of Chamfer's two.
    """
    with torch.no_grad():
        idx = nearest(source, pred)
    near = torch.gather(pred, -2, idx[..., None].expand(*idx.shape, 3))
    d2 = ((source - near) ** 2).sum(-1)
    d = d2 if squared else torch.sqrt(d2 + 1e-9)
    m = source_mask.to(pred.dtype)
    return (d * m).sum(-1) / m.sum(-1).clamp_min(1.0)


def chamfer(target: torch.Tensor, target_mask: torch.Tensor, pred: torch.Tensor, beta: float,
            squared: bool = False) -> torch.Tensor:
    """Chamfer-L1 (``weighted_chamfer``; ``beta`` = weight of pred -> target), or its squared form."""
    if not squared:
        return weighted_chamfer(target, target_mask, pred, beta)

    with torch.no_grad():
        nn_y2x = nearest(pred, target, target_mask)
        nn_x2y = nearest(target, pred)
    near_x = torch.gather(target, -2, nn_y2x[..., None].expand(*nn_y2x.shape, 3))
    near_y = torch.gather(pred, -2, nn_x2y[..., None].expand(*nn_x2y.shape, 3))
    y2x = ((pred - near_x) ** 2).sum(-1)
    x2y = ((target - near_y) ** 2).sum(-1)
    tmask = target_mask.to(pred.dtype)
    n_x = tmask.sum(-1)
    loss = (1 - beta) * (x2y * tmask).sum(-1) / n_x.clamp_min(1.0) + beta * y2x.mean(-1)
    return torch.where(n_x > 0, loss, torch.zeros_like(loss))


@TraPCC.trains_with
def training_recipe(size: str = "default", **options: Any) -> TraPCCRecipe:
    """The recipe ``pcc train trapcc`` uses; model options (``scene_graph``, ``pnet``, ...) and
    training options (:class:`TrainOptions`) both come as ``--option KEY=VALUE``."""
    TraPCC.check_size(size)
    if options.pop("inpainting", True) is False:
        raise ConfigError("trapcc: --no-inpainting is PointPnCNet's ablation; "
                          "use --option scene_graph=none / --option pnet=false")
    model = {k: options.pop(k) for k in list(options) if k in PRESETS[size]}
    return TraPCCRecipe(size, TrainOptions(**options), **model)
