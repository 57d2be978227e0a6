"""``pcc train trapcc``: TraPCC's training recipe (driven by :mod:`pcc_ros.workflows.train`).

The data: every training observation with the pseudo ground truth retrieved for it from the
Whole-GT / Partial-GT pools (:mod:`pcc_ros.data.gt_pools`, through the training kit) and its
scene-graph neighbours.

Loss (Eq. 3): ``CD(coarse, Partial-GT) + CD(detailed, Whole-GT) + MCD(input -> detailed)``.
The Chamfer terms are Chamfer-L1 (Euclidean, averaged both ways; PCN's form) and MCD is
the one-sided input -> detailed mean Euclidean distance. The paper writes squared
distances (Eq. 1, 2); with canonical units (~0.01-0.1) squares make the gradients of the
fine-detail errors vanish, so the training uses the L1 forms (documented in
``docs/trapcc.md``); the evaluation reports the paper's squared L-G / L-I / L-S.
Optional terms (off by default): the left / right symmetry of the detailed output (its shape and,
``balance_weight``, how its points are spread over the two flanks) and, with
``consistency``, the Chamfer between one car's detailed outputs in two neighbouring frames.
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
from pcc_ros.geometry.canonical import mirror_y
from pcc_ros.metrics.balance import track_partners
from pcc_ros.models.base import aspect_scales
from pcc_ros.models.losses import masked_mean, nearest, reflect, symmetry_chamfer, symmetry_density, weighted_chamfer
from pcc_ros.models.recipe import CacheRecipe, CacheTrainOptions, TrainingKit, cache_origin, reflect_points
from pcc_ros.models.trapcc import (
    GEOMETRY_FEATURES,
    PRESETS,
    NeighbourBatch,
    TraPCC,
    nearest_neighbours,
    neighbour_geometry,
    pack_inputs,
    pack_neighbours,
)

log = logging.getLogger(__name__)

#: ``y -> -y`` for the neighbour geometry of :func:`neighbour_geometry`: its lateral offset and the
#: sine of the relative yaw change sign; distance and the cosines do not.
GEOMETRY_MIRROR = np.array([1.0, -1.0, 1.0, -1.0, 1.0, 1.0, 1.0], dtype=np.float32)


@dataclass
class TrainOptions(CacheTrainOptions):
    """Training options of TraPCC (stored in the checkpoint's ``training.recipe``; ``box_aspect``,
    ``held_out`` and ``input_points`` are :class:`~pcc_ros.models.recipe.CacheTrainOptions`'s: with
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
    #: the left / right symmetry the one-flank inputs never show (``docs/pointpncnet.md``, "far side"):
    #: ``mirror_targets`` joins each Whole-GT target with its reflection across the box's x-z plane,
    #: ``symmetry_weight`` weighs the symmetric Chamfer-L1 between the detailed output and its own
    #: reflection (0: off); ``mirror_halves`` joins each Partial-GT half (the coarse output's target)
    #: with its reflection too: retrieval picks the pool entries that best cover the input, so the
    #: retrieved halves lean to the flank the input shows, and the coarse halves C-Net folds the
    #: detailed output around learn that lean (``docs/trapcc.md``, "far side"). All three reflect
    #: across ``mirror_plane``'s plane (:class:`~pcc_ros.models.recipe.CacheTrainOptions`); with
    #: ``"label"`` the retrieved targets (centred on their own box) are also moved to where the car's
    #: labelled box lies in a detector-box crop, so the reflection lands on the car's far flank.
    mirror_targets: bool = False
    symmetry_weight: float = 0.0
    mirror_halves: bool = False
    #: weight of the lateral density symmetry of the detailed output (0: off;
    #: :func:`~pcc_ros.models.losses.symmetry_density`, across ``mirror_plane``'s plane): the Chamfer
    #: terms let the output draw both flanks with most of its points on one
    balance_weight: float = 0.0
    #: probability that a batch is trained in the mirror world (every input, target and neighbour
    #: reflected across the box's x-z plane; ``mirror_plane="box"`` only): the network then has no
    #: reason to prefer one side of the box frame (the shipped weights put their points on +y)
    flip_prob: float = 0.0
    #: weight of the temporal-consistency term (0: off): half of each batch is drawn as usual, the
    #: other half is the same cars in a neighbouring frame (:func:`~pcc_ros.metrics.balance.track_partners`;
    #: a detection without a track id pairs by its matched labelled track, the association a tracker
    #: gives), and the symmetric Chamfer-L1 between the two detailed outputs in the car's box frame is
    #: added. One car's shape does not change between frames; no complete shape is used. The mirrored
    #: targets fill the far flank from each frame's own retrieval, which alone makes it flicker.
    consistency: float = 0.0

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.flip_prob > 0 and self.mirror_plane != "box":  # at set-up, not at the first flipped batch
            raise ConfigError("trapcc: flip_prob reflects across the box's plane; use it with mirror_plane='box'")


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
    #: ``(N, 3, 4)`` each observation's reflection across its car plane (``mirror_plane="label"``;
    #: ``None``: the box's x-z plane for all)
    reflection: np.ndarray | None = None
    #: ``(N, 3, 4)`` where its car's (labelled) box lies in its crop (``mirror_plane="label"``): the
    #: retrieved pseudo ground truth, centred on its own box, is moved there (``None``: the crop's box)
    placement: np.ndarray | None = None
    #: ``(N,)`` the same car's observation in a neighbouring frame (itself when it has none)
    partner: np.ndarray | None = None

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
    reflection: torch.Tensor | None = None  # (B, 3, 4) each input's car plane (None: the box's x-z plane)
    #: ``(B, 3, 4)`` map from each crop's frame to its car's labelled box frame (None: the crop's box is the car's)
    to_car: torch.Tensor | None = None
    #: ``(P,)`` bool, with ``P > 0``: row ``i < P`` and row ``P + i`` are one car in two frames (where True)
    paired: torch.Tensor | None = None

    def to(self, device: torch.device) -> TrainBatch:
        t = [x.to(device, non_blocking=True) for x in (self.points, self.segment)]
        rest = [x.to(device, non_blocking=True) for x in (self.inputs, self.input_mask, self.whole, self.whole_mask,
                                                          self.half, self.half_mask)]
        extra = {k: None if v is None else v.to(device, non_blocking=True)
                 for k, v in (("reflection", self.reflection), ("to_car", self.to_car), ("paired", self.paired))}
        return TrainBatch(*t, self.batch_size, None if self.neighbours is None else self.neighbours.to(device), *rest,
                          **extra)


class TraPCCRecipe(CacheRecipe):
    """What ``pcc train trapcc`` needs (see :mod:`pcc_ros.workflows.train`)."""

    name = "trapcc"
    default_lr = 5e-4

    def __init__(self, size: str = "default", options: TrainOptions | None = None, **model: Any) -> None:
        super().__init__(size, options or TrainOptions())
        if self.options.chamfer not in ("l1", "l2"):
            raise ConfigError(f"trapcc: chamfer must be l1 or l2, got {self.options.chamfer!r}")
        if not 0.0 <= self.options.real_share <= 1.0:
            raise ConfigError(f"trapcc: real_share must be in [0, 1], got {self.options.real_share}")
        if self.options.consistency < 0:
            raise ConfigError(f"trapcc: consistency must be >= 0, got {self.options.consistency}")
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
        per_source, reflections, placements, partners = [], [], [], []
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
            partner = track_partners(np.full(len(sel), ""), c.track_keys(matched=True)[sel], c.meta["frame"][sel])
            partners.append(partner + len(clouds))
            scales = np.ones((len(sel), 3), np.float32)
            if self.aspect is not None:  # inputs in the box-aspect frame; neighbours keep their own frame
                scales = aspect_scales(np.asarray(sizes)[sel], self.aspect, len(sel))
                clouds.extend(nb_clouds[base + int(i)] * sc for i, sc in zip(sel, scales))
            else:
                clouds.extend(nb_clouds[base + int(i)] for i in sel)
            planes = self.car_planes(c)
            whole.append(a["whole_index"][usable])
            front.append(a["front_index"][usable])
            back.append(a["back_index"][usable])
            nbs.append(nb_index[sel])
            geos.append(geo[sel])
            real.append(np.full(len(sel), s > 0))
            per_source.append({"cache": str(c.root), "instances": len(sel), "real": s > 0,
                               "paired": int((partner != np.arange(len(sel))).sum()), **cache_origin(c)})
            if planes is not None:  # how many reflect across their labelled box's plane, how many lack one
                reflections.append(planes.reflections(sel, scales))
                placements.append(planes.placements(sel, scales))
                per_source[-1]["mirror_plane"] = planes.record(sel)
        gt = pools if self.aspect is None else aspect_pools(pools, self.aspect)
        data = TrainData(clouds, np.concatenate(whole), np.concatenate(front), np.concatenate(back),
                         np.concatenate(nbs), np.concatenate(geos), nb_clouds, np.concatenate(real), gt, {},
                         np.concatenate(reflections) if reflections else None,
                         np.concatenate(placements) if placements else None, np.concatenate(partners))
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
        flip = o.flip_prob > 0 and rng.random() < o.flip_prob  # drawn first: the rest of the batch is the same
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
        if flip:
            inputs = [mirror_y(c) for c in inputs]
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
        if data.placement is not None:  # the pseudo ground truth where the car's labelled box lies in the crop
            place = data.placement[chosen]
            whole, hf, hb = (reflect_points(x, place) for x in (whole, hf, hb))
            turned = place[:, 0, 0] < 0  # a detector box heading the other way: its front half is the car's back
            hf[turned], hb[turned] = hb[turned], hf[turned]
            hf_mask[turned], hb_mask[turned] = hb_mask[turned], hf_mask[turned]
        else:
            place = None
        if flip:
            whole, hf, hb = mirror_y(whole), mirror_y(hf), mirror_y(hb)
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
                geometry = data.geometry[int(i)][: len(cl)]
                if flip:  # each neighbour in its own mirrored frame; its place and heading mirrored too
                    cl, geometry = [mirror_y(c) for c in cl], geometry * GEOMETRY_MIRROR
                nb_clouds.append(cl)
                nb_geo.append(geometry)
            neighbours = pack_neighbours(nb_clouds, nb_geo, k)
        points, segment = pack_inputs(inputs)
        return TrainBatch(points, segment, b, neighbours, torch.from_numpy(inp), torch.from_numpy(inp_mask),
                          torch.from_numpy(whole), torch.from_numpy(whole_mask),
                          torch.from_numpy(np.stack([hf, hb], axis=1)),
                          torch.from_numpy(np.stack([hf_mask, hb_mask], axis=1)),
                          None if data.reflection is None else torch.from_numpy(data.reflection[chosen]),
                          None if place is None else torch.from_numpy(invert_affine(place)))

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
        pairs = batch_size // 2 if self.options.consistency > 0 and data.partner is not None else 0
        while True:
            if not pairs:
                chosen = rng.choice(len(data), batch_size, replace=len(data) < batch_size or weights is not None,
                                    p=weights)
                yield self.make_batch(data, chosen, cfg, rng)
                continue
            # half of the batch drawn, the other half the same cars in a neighbouring frame
            chosen = rng.choice(len(data), pairs, replace=len(data) < pairs or weights is not None, p=weights)
            batch = self.make_batch(data, np.concatenate([chosen, data.partner[chosen]]), cfg, rng)
            batch.paired = torch.from_numpy(data.partner[chosen] != chosen)
            yield batch

    # ---- loss

    def loss(self, net: nn.Module, batch: TrainBatch) -> tuple[torch.Tensor, dict[str, float]]:
        return trapcc_loss(net, batch, self.options)


def invert_affine(maps: np.ndarray) -> np.ndarray:
    """The inverses of ``(..., 3, 4)`` affine maps ``x -> A x + t``: ``x -> A^-1 x - A^-1 t``."""
    inv = np.linalg.inv(maps[..., :3].astype(np.float64))
    return np.concatenate([inv, -(inv @ maps[..., 3:].astype(np.float64))], -1).astype(np.float32)


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
    target, target_mask = batch.whole, batch.whole_mask
    if options.mirror_targets:
        target = torch.cat([target, reflect(target, batch.reflection)], 1)
        target_mask = torch.cat([target_mask, target_mask], 1)
    whole = chamfer(target, target_mask, sub, 0.5, squared)
    has_whole = batch.whole_mask.any(-1)
    l_whole = masked_mean(whole, has_whole)
    l_input = masked_mean(one_sided(batch.inputs, batch.input_mask, detailed, squared), batch.input_mask.any(-1))
    loss = options.weight_whole * l_whole + options.weight_input * l_input
    stats = {"whole": float(l_whole.detach()), "input": float(l_input.detach())}
    if "coarse" in out:
        half, half_mask = batch.half, batch.half_mask
        if options.mirror_halves:  # (B, 2, 2H, 3): each half with its reflection (the front half stays in front)
            half = torch.cat([half, reflect(half, batch.reflection)], 2)
            half_mask = torch.cat([half_mask, half_mask], 2)
        part = chamfer(half, half_mask, out["coarse"], 0.5, squared)  # (B, 2)
        use = out["present"] & batch.half_mask.any(-1)
        l_part = masked_mean(part, use)
        loss = loss + options.weight_partial * l_part
        stats["partial"] = float(l_part.detach())
    if options.symmetry_weight > 0:
        symmetry = symmetry_chamfer(sub, batch.reflection)
        loss = loss + options.symmetry_weight * symmetry
        stats["symmetry"] = float(symmetry.detach())
    if options.balance_weight > 0:
        balance = symmetry_density(detailed, batch.reflection)
        loss = loss + options.balance_weight * balance
        stats["balance"] = float(balance.detach())
    if options.consistency > 0 and batch.paired is not None:
        gap = track_pair_chamfer(sub, batch.paired, batch.to_car)
        loss = loss + options.consistency * gap
        stats["consistency"] = float(gap.detach())
    stats["loss"] = float(loss.detach())
    return loss, stats


def track_pair_chamfer(points: torch.Tensor, paired: torch.Tensor, to_car: torch.Tensor | None = None
                       ) -> torch.Tensor:
    """Mean symmetric Chamfer-L1 between rows ``i`` and ``P + i`` of ``points`` ``(B, M, 3)`` over the
    ``P = len(paired)`` pairs where ``paired`` (one car in two frames), each row first mapped to its car's
    box frame by ``to_car`` (``(B, 3, 4)``; ``None``: the crop's box is the car's). The car's shape does
    not change between frames, so its completions should not either (``pcc eval``'s ``consistency``)."""
    if to_car is not None:
        points = reflect(points, to_car)
    p = paired.shape[0]
    a, b = points[:p], points[p:2 * p]
    full = torch.ones(a.shape[:-1], dtype=torch.bool, device=a.device)
    return masked_mean(weighted_chamfer(a, full, b, 0.5), paired)


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
