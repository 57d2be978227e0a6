"""PointPnCNet: self-supervised point cloud completion by inpainting (Partition-and-Completion).

The network (paper Sec. 3.2, appendix 7.1) has two streams over one canonical partial cloud:

* global: a PCN encoder over all points -> embedding ``e_g``;
* local: the cloud split into the eight canonical octants (with a small overlap, so points
  near a plane belong to both sides), each octant with enough points encoded by a narrow
  PCN encoder (same weights for every octant), an attention MLP weighting the octant
  embeddings (absent octants masked out), aggregated to ``P_l``.

They are fused by a channel-wise max ``P = max(e_g, P_l)``. A global folding decoder turns
``P`` into the whole car; a local folding decoder turns ``[P ; one-hot(octant)]`` into the
points of each octant. The completion is the union of both outputs.

Training (see :class:`PointPnCNetRecipe`) never sees a complete shape: whole octants are
removed from the input at random (synthetic occlusion) and the output is compared, with the
asymmetric weighted Chamfer distance (beta = 0.25 on prediction -> target), to the ORIGINAL
partial cloud and to the other views of the same track (multi-view consistency); the local
loss covers only octants present in the original view (>= 4 points). Because the network
cannot tell synthetic from natural occlusion, it learns to fill in both.

Two sizes from one config (``size``): ``paper`` (the published widths and point counts:
4096 global + 8 x 512 local = 8192 points, up to 3096 input points) and ``default``, a
narrower model with 2048 output points that meets the CPU speed target. Inference encodes
the real points of each car (packed batch, segment max-pool; no resampling of 150 points
up to 3096 duplicates), capped at ``max_input_points`` by a content-seeded random subset.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
import torch
from torch import nn

from pcc_ros.errors import ConfigError
from pcc_ros.geometry.canonical import mirror_y
from pcc_ros.models.base import (
    CacheRecipe,
    CacheTrainOptions,
    SceneContext,
    TorchCompleter,
    aspect_scales,
    cache_origin,
    resample_cloud,
)
from pcc_ros.models.losses import masked_mean, symmetry_chamfer, weighted_chamfer
from pcc_ros.models.pointpncnet_network import (
    NUM_REGIONS,
    Packed,
    PointPnCNetNet,
    pack,
    region_masks,
)
from pcc_ros.models.recipe import BOX_REFLECTION, reflect_points
from pcc_ros.models.registry import register

log = logging.getLogger(__name__)

#: The two sizes. ``paper``: PCN widths (encoder 3-128-256 / 512-1024, decoder FC 1024-1024,
#: folding 512-512), local streams at 1/8 of the hidden width, 4096 + 8 x 512 points.
#: ``default``: the CPU size; the folding MLP over the 1029-wide features is what dominates
#: at paper size, so it is 64 wide here and produces 1024 + 8 x 128 points.
PRESETS: dict[str, dict[str, Any]] = {
    "paper": {
        "encoder_widths1": [128, 256],
        "encoder_widths2": [512, 1024],
        "local_encoder_widths1": [16, 32],
        "local_encoder_widths2": [64, 1024],
        "attention_hidden": 128,
        "decoder_fc_widths": [1024, 1024],
        "global_coarse_points": 1024,
        "global_grid_size": 2,
        "fold_widths": [512, 512],
        "local_decoder_fc_widths": [128, 128],
        "local_coarse_points": 128,
        "local_grid_size": 2,
        "local_fold_widths": [64, 64],
        "grid_scale": 0.05,
        "local_grid_scale": 0.025,
        "region_overlap": 0.005,
        "min_region_points": 4,
        "max_input_points": 3096,
    },
    "default": {
        "encoder_widths1": [64, 128],
        "encoder_widths2": [128, 256],
        "local_encoder_widths1": [16, 32],
        "local_encoder_widths2": [32, 256],
        "attention_hidden": 64,
        "decoder_fc_widths": [256, 256],
        "global_coarse_points": 256,
        "global_grid_size": 2,
        "fold_widths": [64, 64],
        "local_decoder_fc_widths": [64, 64],
        "local_coarse_points": 32,
        "local_grid_size": 2,
        "local_fold_widths": [32, 32],
        "grid_scale": 0.05,
        "local_grid_scale": 0.025,
        "region_overlap": 0.005,
        "min_region_points": 4,
        "max_input_points": 1024,
    },
}


# --------------------------------------------------------------------------- completer


@register("pointpncnet")
class PointPnCNet(TorchCompleter):
    """PointPnCNet completer: canonical partial clouds in, ``Mg + 8 Ml`` canonical points out.

    ``size`` picks a preset (``default`` or ``paper``); any other key overrides the preset.
    """

    #: The named sizes of the network.
    presets = PRESETS

    def build_model(self) -> PointPnCNetNet:
        cap = int(self.config["max_input_points"])
        if cap < 1:
            raise ConfigError(f"pointpncnet: max_input_points must be >= 1, got {cap}")
        return PointPnCNetNet(self.config)

    @property
    def num_output_points(self) -> int:
        return self.model.num_global_points + NUM_REGIONS * self.model.num_local_points

    def prepare(self, clouds: Sequence[np.ndarray]) -> list[np.ndarray]:
        """Cap each cloud at ``max_input_points`` (content-seeded subset); smaller ones stay as they are."""
        cap = int(self.config["max_input_points"])
        return [c if len(c) <= cap else resample_cloud(c, cap) for c in clouds]

    def forward_batch(self, clouds: list[np.ndarray], contexts: list[SceneContext | None]) -> list[np.ndarray]:
        fast = self.inference_path != "reference"  # the original path keeps its mask and sort (the comparison)
        packed = pack(self.prepare(clouds), float(self.config["region_overlap"]), pairs=fast).to(self.device)
        out = torch.empty(packed.batch_size, self.num_output_points, 3, device=self.device)
        self.model(packed.points, packed.segment, packed.regions, packed.batch_size, packed.pairs, out=out)
        return list(out.float().cpu().numpy())


# --------------------------------------------------------------------------- training


def remove_regions(
    cloud: np.ndarray, regions: np.ndarray, drop_prob: float, min_points: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Synthetic occlusion: drop each present octant with ``drop_prob`` (all its points).

    At least one present octant is always kept, so the input never becomes empty.
    Returns the remaining points and their octant masks.
    """
    present = regions.sum(0) >= min_points
    drop = present & (rng.random(NUM_REGIONS) < drop_prob)
    if present.any() and not (present & ~drop).any():
        drop[rng.choice(np.flatnonzero(present))] = False
    if not drop.any():
        return cloud, regions
    keep = ~regions[:, drop].any(1)
    if not keep.any():  # every point lay in a dropped octant's overlap band: keep the input
        return cloud, regions
    return cloud[keep], regions[keep]


@dataclass
class TrainOptions(CacheTrainOptions):
    """Training hyper-parameters of PointPnCNet (stored in the checkpoint's ``training``; its ``box_aspect``,
    ``held_out`` and ``input_points`` are :class:`~pcc_ros.models.base.CacheTrainOptions`)."""

    drop_prob: float = 0.2
    beta: float = 0.25
    loss_points: int = 256
    local_loss_points: int = 64
    views: int = 4
    local_weight: float = 1.0
    #: inputs and targets from different crops of the same observation: ``None`` (default) uses
    #: each view whole as the pseudo ground truth; a number takes as targets only the view's points
    #: inside its box grown by this many metres with the lowest ``target_ground_margin`` metres
    #: dropped, while the input keeps the whole crop. Training on node crops
    #: (``pcc extract --node-crop``: margin 0.1, ground 0.05) with ``target_margin=0`` gives the
    #: node's inputs (a frame of ground returns and neighbours' points included) and the tight
    #: crops' targets (the car's own returns), so the network learns to leave the frame out.
    target_margin: float | None = None
    target_ground_margin: float = 0.1
    #: the left / right symmetry of a car, which the partial targets alone never teach: the
    #: observations of a track are all seen from one flank, so the prediction -> target term pulls
    #: every generated point to the seen side (``docs/pointpncnet.md``, "far side").
    #: ``mirror_targets``: each pseudo-ground-truth view is joined by its reflection across the
    #: box's x-z plane (the mirror prior as a target, on the global and the octant losses);
    mirror_targets: bool = False
    #: ``flip_prob``: each training group (input and targets) is reflected with this probability, so
    #: the right-hand traffic's seen flank (+y in 72 % of SynthCars observations) is no prior;
    flip_prob: float = 0.0
    #: ``symmetry_weight``: weight of the symmetric Chamfer-L1 between the global output and its own
    #: reflection (0: off).
    symmetry_weight: float = 0.0
    # mirror_plane (CacheTrainOptions): the plane all three reflect across, the box's or the labelled box's


class PlaneView(NamedTuple):
    """A training view whose car's centre plane is not its box's: its points and the ``(3, 4)``
    affine reflection ``[M | t]`` across that plane (in the view's frame, aspect scaling included)."""

    points: np.ndarray
    reflection: np.ndarray


def _points(view: np.ndarray | PlaneView) -> np.ndarray:
    return view.points if isinstance(view, PlaneView) else view


def _reflection(view: np.ndarray | PlaneView) -> np.ndarray:
    return view.reflection if isinstance(view, PlaneView) else BOX_REFLECTION


def _flip(view: np.ndarray | PlaneView) -> np.ndarray | PlaneView:
    """A view reflected across its box's x-z plane (F), its car's plane with it (F A F)."""
    if not isinstance(view, PlaneView):
        return mirror_y(view)
    f = BOX_REFLECTION[:, :3]
    m, t = view.reflection[:, :3], view.reflection[:, 3]
    return PlaneView(mirror_y(view.points), np.concatenate([f @ m @ f, (f @ t)[:, None]], axis=1))


def target_flags(points: np.ndarray, size: np.ndarray, margin: float, ground_margin: float) -> np.ndarray:
    """Which canonical ``points`` of one observation lie inside its box grown by ``margin`` metres
    with the lowest ``ground_margin`` metres dropped (the crop ``pcc extract --margin M
    --ground-margin G`` makes); ``size``: the box's length, width, height in metres."""
    length, width, height = (float(s) for s in size)
    half = np.array([length / 2 + margin, width / 2 + margin, height / 2 + margin]) / length
    low = (-height / 2 - margin + ground_margin) / length
    p = np.asarray(points)
    return (np.abs(p[:, 0]) <= half[0]) & (np.abs(p[:, 1]) <= half[1]) & (p[:, 2] >= low) & (p[:, 2] <= half[2])


def view_targets(view: np.ndarray | PlaneView) -> np.ndarray:
    """The pseudo-ground-truth points of a training view: all of an ``(N, 3)`` view, the flagged
    rows of an ``(N, 4)`` one (fourth column: :func:`target_flags`, see ``target_margin``)."""
    view = _points(view)
    return view if view.shape[1] == 3 else view[view[:, 3] > 0, :3]


def region_subsets(
    regions: np.ndarray, per_region: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """A random subset of at most ``per_region`` points of every octant, in one vectorised pass.

    Returns ``(point_index, region_index)`` pairs plus each pair's slot within its octant
    as ``(pairs (K, 2), slot (K,))``.
    """
    point_idx, region_idx = np.nonzero(regions)
    order = np.lexsort((rng.random(len(point_idx)), region_idx))  # by region, random inside
    point_idx, region_idx = point_idx[order], region_idx[order]
    first = np.searchsorted(region_idx, region_idx, side="left")
    slot = np.arange(len(region_idx)) - first
    keep = slot < per_region
    return np.stack([point_idx[keep], region_idx[keep]], axis=1), slot[keep]


@dataclass
class TrainBatch:
    """One PointPnCNet training batch: synthetically occluded inputs and original views."""

    inputs: Packed
    target: torch.Tensor  # (B, V, N, 3) original views (subsampled), padded
    target_mask: torch.Tensor  # (B, V, N) valid target points
    local_target: torch.Tensor  # (B, V, 8, L, 3) points of each octant of each original view
    local_mask: torch.Tensor  # (B, V, 8, L)
    region_present: torch.Tensor  # (B, V, 8) octants present in the original view (>= min points)
    view_mask: torch.Tensor  # (B, V) which views exist
    reflection: torch.Tensor | None = None  # (B, 3, 4) each input's car plane (None: the box's x-z plane)

    def to(self, device: torch.device) -> TrainBatch:
        tensors = (self.target, self.target_mask, self.local_target, self.local_mask, self.region_present,
                   self.view_mask)
        reflection = None if self.reflection is None else self.reflection.to(device, non_blocking=True)
        return TrainBatch(self.inputs.to(device), *(t.to(device, non_blocking=True) for t in tensors),
                          reflection=reflection)


def make_train_batch(
    groups: Sequence[Sequence[np.ndarray]],
    cfg: dict[str, Any],
    options: TrainOptions,
    rng: np.random.Generator,
) -> TrainBatch:
    """Assemble a batch from groups of views of one track each (canonical partial clouds).

    For each group one view is the input (capped at ``options.input_points``, then random octant
    removal); up to ``options.views`` views (the input's own original view first) are the
    pseudo ground truth, each subsampled to at most ``options.loss_points`` points (and
    ``options.local_loss_points`` per octant for the local loss). A view with a fourth column
    is input whole and target only where that column is set (:func:`view_targets`). A
    :class:`PlaneView` is reflected across its own car plane (``mirror_targets``, the symmetry
    term) instead of the box's. Only observed partial clouds are used: this function never sees a
    complete shape.
    """
    overlap = float(cfg["region_overlap"])
    min_points = int(cfg["min_region_points"])
    cap = int(options.input_points or cfg["max_input_points"])
    inputs, input_regions, targets, reflections = [], [], [], []
    for views in groups:  # loop over instances of a batch (tens); all per-point work is vectorised
        if options.flip_prob > 0 and rng.random() < options.flip_prob:
            views = [_flip(v) for v in views]
        k = int(rng.integers(len(views)))
        others = [v for i, v in enumerate(views) if i != k]
        order = rng.permutation(len(others))[: max(0, options.views - 1)]
        picked = [views[k], *(others[i] for i in order)]
        chosen = [view_targets(v) for v in picked]
        if options.mirror_targets:
            chosen = [np.concatenate([x, reflect_points(x, _reflection(v))]) for x, v in zip(chosen, picked)]
        targets.append(chosen)
        reflections.append(_reflection(views[k]))
        cloud = _points(views[k])[:, :3]
        if len(cloud) > cap:
            cloud = cloud[rng.choice(len(cloud), cap, replace=False)]
        cloud, cloud_regions = remove_regions(cloud, region_masks(cloud, overlap), options.drop_prob, min_points, rng)
        inputs.append(cloud)
        input_regions.append(cloud_regions)

    b = len(groups)
    v = max(len(t) for t in targets)
    n = min(options.loss_points, max(len(x) for t in targets for x in t))
    per_region = options.local_loss_points
    target = np.zeros((b, v, n, 3), dtype=np.float32)
    mask = np.zeros((b, v, n), dtype=bool)
    local_target = np.zeros((b, v, NUM_REGIONS, per_region, 3), dtype=np.float32)
    local_mask = np.zeros((b, v, NUM_REGIONS, per_region), dtype=bool)
    present = np.zeros((b, v, NUM_REGIONS), dtype=bool)
    view_mask = np.zeros((b, v), dtype=bool)
    for i, views in enumerate(targets):
        for j, x in enumerate(views):
            regions = region_masks(x, overlap)
            present[i, j] = regions.sum(0) >= min_points
            pairs, slot = region_subsets(regions, per_region, rng)
            local_target[i, j, pairs[:, 1], slot] = x[pairs[:, 0]]
            local_mask[i, j, pairs[:, 1], slot] = True
            sub = x if len(x) <= n else x[rng.choice(len(x), n, replace=False)]
            target[i, j, : len(sub)] = sub
            mask[i, j, : len(sub)] = True
            view_mask[i, j] = True
    planes = any(isinstance(v, PlaneView) for views in groups for v in views)
    return TrainBatch(
        pack(inputs, overlap, input_regions),
        *(torch.from_numpy(a) for a in (target, mask, local_target, local_mask, present, view_mask)),
        reflection=torch.from_numpy(np.stack(reflections)) if planes else None,
    )


def inpainting_loss(
    net: nn.Module, batch: TrainBatch, beta: float, local_weight: float = 1.0, symmetry_weight: float = 0.0
) -> tuple[torch.Tensor, dict[str, float]]:
    """Inpainting-global + inpainting-local losses with multi-view consistency.

    Global: ``L_wcd(X_j, Y_g)`` for every view ``j`` of the track. Local: the sum over
    octants ``i`` present in view ``j`` of ``L_wcd(X_j^i, Y_l^i)``. Both are averaged over
    views and instances (the paper sums over views; the average keeps the scale independent
    of how many views a track happens to have). ``symmetry_weight`` adds that weight times the
    symmetric Chamfer-L1 between ``Y_g`` and its reflection across the box's x-z plane (across each
    input's car plane where the batch has ``reflection``): a car is left / right symmetric, and
    nothing else in the loss asks for the side the sensor did not see.
    """
    inp = batch.inputs
    y_global, y_local, _ = net(inp.points, inp.segment, inp.regions, inp.batch_size)
    b, v = batch.view_mask.shape
    g = weighted_chamfer(batch.target, batch.target_mask, y_global[:, None].expand(b, v, -1, 3), beta)
    global_loss = masked_mean(g, batch.view_mask)
    pred = y_local[:, None].expand(b, v, -1, -1, 3)
    per_region = weighted_chamfer(batch.local_target, batch.local_mask, pred, beta)  # (B, V, 8)
    per_view = (per_region * batch.region_present).sum(-1)
    local_loss = masked_mean(per_view, batch.view_mask)
    loss = global_loss + local_weight * local_loss
    stats = {"loss": 0.0, "global": float(global_loss.detach()), "local": float(local_loss.detach())}
    if symmetry_weight > 0:
        symmetry = symmetry_chamfer(y_global, batch.reflection)
        loss = loss + symmetry_weight * symmetry
        stats["symmetry"] = float(symmetry.detach())
    stats["loss"] = float(loss.detach())
    return loss, stats


class PointPnCNetRecipe(CacheRecipe):
    """What ``pcc train pointpncnet`` needs: model, loss and batch sampler.

    ``pcc_ros.workflows.train`` is generic: it asks the backend class for ``training_recipe(...)``
    (:meth:`PointPnCNet.training_recipe`) and drives any object with this shape.
    """

    name = "pointpncnet"

    def __init__(self, size: str, inpainting: bool = True, options: TrainOptions | None = None) -> None:
        super().__init__(size, options or TrainOptions())
        if not inpainting:
            self.options.drop_prob = 0.0
        self.inpainting = inpainting
        #: per training cache: its origin and crop, what was kept (``data_summary``)
        self.sources: list[dict[str, Any]] = []
        self.held_out: dict[str, Any] = {"sources": [], "checked_caches": []}

    def build_completer(self, device: str) -> PointPnCNet:
        return PointPnCNet(device=device, size=self.size)

    def settings(self) -> dict[str, Any]:
        return {"inpainting": self.inpainting}

    def data_summary(self) -> dict[str, Any]:
        """The caches trained on (origin, crop, observations kept), the held-out sources and the
        target crop, for the checkpoint's ``training.data_summary``."""
        target = None
        if self.options.target_margin is not None:
            target = {"margin": self.options.target_margin, "ground_margin": self.options.target_ground_margin}
        return {"sources": list(self.sources), "target_crop": target, "held_out": dict(self.held_out),
                "box_aspect": self.aspect_record(), "complete_shapes_used": False}

    def _check_cache(self, cache: Any) -> dict[str, Any]:
        """Refuse a held-out cache and a cache whose crop lacks the targets' points; its origin."""
        held = self.check_held_out([cache])
        self.held_out = {"sources": held["sources"],
                         "checked_caches": [*self.held_out["checked_caches"], *held["checked_caches"]]}
        origin = cache_origin(cache)
        tm = self.options.target_margin
        if tm is not None:
            crop = origin["crop"]
            margin, ground = crop.get("margin"), crop.get("ground_margin")
            if margin is None or ground is None:
                raise ConfigError(f"pointpncnet: target_margin needs the crop of {cache.root} (its pcc extract record "
                                  "has no margin / ground_margin)")
            tg = self.options.target_ground_margin
            if tm > margin + 1e-9 or (tg - tm) < (ground - margin) - 1e-9:
                raise ConfigError(f"pointpncnet: the target crop (margin {tm}, ground margin {tg}) reaches outside "
                                  f"the crop of {cache.root} (margin {margin}, ground margin {ground}); extract the "
                                  "cache with a wider crop (pcc extract --node-crop) or narrow the targets")
        return origin

    def training_data(self, cache: Any, split: str, min_points: int = 10) -> list[list[np.ndarray]]:
        """Groups of canonical partial views from an instance cache (``pcc_ros.data.instances``).

        Tracked observations form the paper's multi-view groups (20 sequential observations
        of a track); observations without a track are single-view groups. The cache holds
        no complete shapes, so none can reach training from here.
        """
        origin = self._check_cache(cache)
        indices = cache.indices(split, min_points=min_points)
        groups = cache.multiview_groups(indices, group_size=20, min_views=1)
        grouped = np.zeros(len(cache), dtype=bool)
        for g in groups:
            grouped[g] = True
        singles = [np.array([i]) for i in indices[~grouped[indices]]]
        sizes = np.asarray(cache.meta["box_size"], dtype=np.float64)
        scales = np.ones((len(cache), 3), dtype=np.float32)
        aspect = self.fix_aspect(sizes[indices])  # the first (main) training data fixes it for every cache mixed in
        if aspect is not None:
            scales[indices] = aspect_scales(sizes[indices], aspect, len(indices))
        tm, tg = self.options.target_margin, self.options.target_ground_margin
        planes = self.car_planes(cache)
        moved = None if planes is None else planes.moved  # a box's own plane: those views stay plain arrays

        def view(i: int) -> np.ndarray | PlaneView:
            points = np.asarray(cache.points(i), dtype=np.float32)
            if tm is None:
                out = points * scales[i]
            else:
                flags = target_flags(points, sizes[i], tm, tg)  # in the canonical frame, before the aspect
                out = np.concatenate([points * scales[i], flags[:, None].astype(np.float32)], axis=1)
            if moved is not None and moved[i]:
                return PlaneView(out, planes.reflection(i, scales[i]))
            return out

        out, dropped = [], 0
        for g in [*groups, *singles]:  # loop over observations (tens of thousands); the work per point is vectorised
            views = [view(int(i)) for i in g]
            if tm is not None:  # a view whose target crop keeps too few points is no pseudo ground truth
                kept = [v for v in views if int(_points(v)[:, 3].sum()) >= min_points]
                dropped += len(views) - len(kept)
                views = kept
            if views:
                out.append(views)
        record = {"cache": str(cache.root), **origin, "split": split, "groups": len(out),
                  "observations": sum(len(g) for g in out), "dropped_few_target_points": dropped}
        if planes is not None:  # how many views reflect across their labelled box's plane, how many lack one
            used = np.concatenate([*groups, *singles]) if len(groups) + len(singles) else np.zeros(0, int)
            record["mirror_plane"] = planes.record(used)
        self.sources.append(record)
        return out

    def batches(
        self, groups: Sequence[Sequence[np.ndarray]], batch_size: int, cfg: dict[str, Any], rng: np.random.Generator
    ) -> Iterator[TrainBatch]:
        """Endless stream of batches: groups drawn without replacement, reshuffled every epoch.

        ``groups`` holds, per track (or per single observation), its canonical partial views.
        """
        if not groups:
            raise ConfigError("no training groups: the training split is empty")
        while True:
            order = rng.permutation(len(groups))
            if len(order) < batch_size:  # tiny data set: sample with replacement
                order = rng.integers(len(groups), size=batch_size)
            for start in range(0, len(order) - batch_size + 1, batch_size):
                chosen = [groups[i] for i in order[start : start + batch_size]]
                yield make_train_batch(chosen, cfg, self.options, rng)

    def loss(self, net: nn.Module, batch: TrainBatch) -> tuple[torch.Tensor, dict[str, float]]:
        return inpainting_loss(net, batch, self.options.beta, self.options.local_weight, self.options.symmetry_weight)


@PointPnCNet.trains_with
def training_recipe(size: str = "default", inpainting: bool = True, **options: Any) -> PointPnCNetRecipe:
    """The training recipe ``pcc train pointpncnet`` uses (see :mod:`pcc_ros.workflows.train`)."""
    return PointPnCNetRecipe(size, inpainting, TrainOptions(**options))
