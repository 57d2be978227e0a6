"""PointPnCNet's network (:class:`PointPnCNetNet`) and its packed batches (:func:`pack`).

The completer, the presets and the training recipe are in :mod:`pcc_ros.models.pointpncnet`;
the architecture is described there. The network runs on every inference path of
:mod:`pcc_ros.models.inference`; on the ``compiled`` path its whole forward is one call of
:func:`pcc_ros.models.kernels.pointpncnet_infer`, with the weights this module derives from its
layers (:meth:`PointPnCNetNet.kernel_weights`).
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import nn

from pcc_ros.errors import ConfigError
from pcc_ros.geometry.partitions import octant_masks
from pcc_ros.models.inference import as_numpy, kernels_for
from pcc_ros.models.layers import FoldingDecoder, PCNEncoder, SharedMLP, dense_weights, fast_inference
from pcc_ros.scratch import Scratch

#: The octants of the local stream.
NUM_REGIONS = 8
#: The whole-network kernel's work memory (:meth:`PointPnCNetNet._forward_compiled`), per thread.
SCRATCH = Scratch()


def region_masks(points: np.ndarray, overlap: float) -> np.ndarray:
    """``(N, 8)`` octant membership of canonical points (the shared partition definition)."""
    return np.asarray(octant_masks(points, overlap), dtype=bool)


def octant_pairs(points: np.ndarray, lengths: np.ndarray, overlap: float) -> tuple[np.ndarray, np.ndarray]:
    """Every (point, octant) membership of a packed batch, grouped by instance and octant.

    The same memberships as ``region_masks`` (``np.nonzero`` of it), without building and
    scanning the ``(P, 8)`` mask: a point lies in its own octant
    (:func:`~pcc_ros.geometry.partitions.octant_index`), and only points within ``overlap`` of a
    coordinate plane (a few per cent) belong to more (one compiled pass and a counting sort,
    :func:`pcc_ros.models.kernels.octant_pairs`). Returns ``(point_index, local_segment)`` with
    ``local_segment = instance * 8 + octant`` ascending, so the local encoder gets whole
    segments in order.
    """
    from pcc_ros.models import kernels  # numba: heavy, only for inference

    points = np.ascontiguousarray(points, dtype=np.float32)
    return kernels.octant_pairs(points, np.asarray(lengths, dtype=np.int64), np.float32(overlap))


# --------------------------------------------------------------------------- network


class PointPnCNetNet(nn.Module):
    """The two-stream encoder / two-stream decoder network on packed batches."""

    def __init__(self, cfg: dict[str, Any]) -> None:
        super().__init__()
        self.min_region_points = int(cfg["min_region_points"])
        self.global_encoder = PCNEncoder(cfg["encoder_widths1"], cfg["encoder_widths2"])
        embed = self.global_encoder.out_dim
        self.local_encoder = PCNEncoder(cfg["local_encoder_widths1"], cfg["local_encoder_widths2"])
        if self.local_encoder.out_dim != embed:
            raise ConfigError(
                f"local_encoder_widths2 must end with the global embedding width {embed} "
                f"(they are fused by a channel-wise max), got {self.local_encoder.out_dim}"
            )
        self.attention = SharedMLP(embed, [int(cfg["attention_hidden"]), 1])
        self.global_decoder = FoldingDecoder(
            embed,
            cfg["decoder_fc_widths"],
            int(cfg["global_coarse_points"]),
            int(cfg["global_grid_size"]),
            cfg["fold_widths"],
            float(cfg["grid_scale"]),
        )
        self.local_decoder = FoldingDecoder(
            embed + NUM_REGIONS,
            cfg["local_decoder_fc_widths"],
            int(cfg["local_coarse_points"]),
            int(cfg["local_grid_size"]),
            cfg["local_fold_widths"],
            float(cfg["local_grid_scale"]),
        )
        self.register_buffer("one_hot", torch.eye(NUM_REGIONS), persistent=False)
        self.embed_dim = embed
        #: how inference runs (:mod:`pcc_ros.models.inference`; its completer sets it)
        self.inference_path = "auto"

    @property
    def num_global_points(self) -> int:
        return self.global_decoder.num_points

    @property
    def num_local_points(self) -> int:
        """Points per octant."""
        return self.local_decoder.num_points

    def forward(
        self,
        points: torch.Tensor,
        segment: torch.Tensor,
        regions: torch.Tensor | None,
        batch_size: int,
        pairs: tuple[torch.Tensor, torch.Tensor] | None = None,
        out: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Complete a packed batch.

        Args:
            points: ``(P, 3)`` canonical points of all instances, concatenated.
            segment: ``(P,)`` instance index of each point, sorted, in ``[0, batch_size)``.
            regions: ``(P, 8)`` bool octant membership (a point may be in two octants).
            batch_size: number of instances ``B``.
            pairs: instead of ``regions``, its memberships as (point index, instance * 8 +
                octant) sorted by the latter (:func:`octant_pairs`; inference).
            out: ``(B, Mg + 8 Ml, 3)``, where both decoders write (the global points, then the
                octants'); the returned clouds are then views of it.

        Returns:
            ``global (B, Mg, 3)``, ``local (B, 8, Ml, 3)`` and ``present (B, 8)`` (octants
            with at least ``min_region_points`` input points, the ones the local stream used).
        """
        b = batch_size
        if pairs is not None and out is not None and fast_inference(self):
            present = self._forward_compiled(points, segment, pairs, b, out)
            if present is not None:
                mg = self.num_global_points
                return out[:, :mg], out[:, mg:].view(b, NUM_REGIONS, -1, 3), present
        e_g = self.global_encoder(points, segment, b)
        if pairs is not None:
            point_idx, local_segment = pairs
        else:
            point_idx, region_idx = regions.nonzero(as_tuple=True)
            local_segment = segment[point_idx] * NUM_REGIONS + region_idx
            if self.inference_path == "reference":  # segment_reduce needs sorted segments; the scatter max does not
                order = torch.argsort(local_segment, stable=True)
                point_idx, local_segment = point_idx[order], local_segment[order]
        if points.device.type == "cpu" and points.dtype == torch.float32 and not points.requires_grad:
            # numpy's gather: a fifth of torch's here (numpy has no bfloat16: half precision gathers in torch)
            local_points = torch.from_numpy(points.numpy().take(point_idx.numpy(), axis=0))
        else:
            local_points = points[point_idx]
        e_l = self.local_encoder(local_points, local_segment, b * NUM_REGIONS).view(b, NUM_REGIONS, -1)
        counts = torch.bincount(local_segment, minlength=b * NUM_REGIONS).view(b, NUM_REGIONS)
        present = counts >= self.min_region_points
        logits = self.attention(e_l).squeeze(-1)
        # the dtype's lowest value, not a literal: -1e9 overflows float16 (half precision on a GPU)
        logits = logits.masked_fill(~present, torch.finfo(logits.dtype).min)
        weights = torch.softmax(logits, dim=1) * present
        p_l = (weights[..., None] * e_l).sum(1)
        any_present = present.any(1, keepdim=True)
        fused = torch.where(any_present, torch.maximum(e_g, p_l), e_g)

        mg = self.num_global_points
        _, y_global = self.global_decoder(fused, None if out is None else out[:, :mg])
        code = torch.cat(
            [fused[:, None, :].expand(b, NUM_REGIONS, self.embed_dim), self.one_hot[None].expand(b, -1, -1)], dim=2
        ).reshape(b * NUM_REGIONS, -1)
        _, y_local = self.local_decoder(code, None if out is None else out[:, mg:])
        return y_global, y_local.view(b, NUM_REGIONS, -1, 3), present

    def warm_up_compiled(self) -> None:
        """Compile :meth:`_forward_compiled`'s kernel now (a batch of one tiny cloud, the argument
        types of every later call), not on the first real batch."""
        corners = np.array(list(itertools.product((-0.5, 0.5), repeat=3)), np.float32)
        packed = pack([np.repeat(corners, self.min_region_points, axis=0)], 0.0, pairs=True)
        out = torch.empty(1, self.num_global_points + NUM_REGIONS * self.num_local_points, 3)
        with torch.inference_mode():
            self._forward_compiled(packed.points, packed.segment, packed.pairs, 1, out)

    def kernel_weights(self):
        """The network for :func:`pcc_ros.models.kernels.pointpncnet_infer`:
        :class:`pcc_ros.models.kernels.NetworkWeights`, derived from its layers (each layer's
        own ``kernel_weights``, kept while its parameters are unchanged), or None where a layer
        is not the structure the compiled loops run."""
        from pcc_ros.models.kernels import NetworkWeights

        parts = (self.global_encoder.kernel_weights(), self.local_encoder.kernel_weights(),
                 self.global_decoder.kernel_weights(1), self.local_decoder.kernel_weights(NUM_REGIONS))
        if any(p is None for p in parts):
            return None
        global_encoder, local_encoder, global_decoder, local_decoder = parts
        return NetworkWeights(global_encoder, local_encoder, dense_weights(self.attention), global_decoder,
                              local_decoder, self.min_region_points)

    def _forward_compiled(self, points: torch.Tensor, segment: torch.Tensor, pairs: tuple[torch.Tensor, torch.Tensor],
                          b: int, out: torch.Tensor) -> torch.Tensor | None:
        """:meth:`forward` in one compiled call (:func:`pcc_ros.models.kernels.pointpncnet_infer`:
        the layers' compiled loops and the steps between them, no Python or torch operator in
        between), writing ``out``; returns ``present``, or None where it does not apply (not the
        ``compiled`` path, tensors the compiled loops do not run on, other layers, segments not
        sorted, ``out`` not a contiguous float32 CPU tensor) and the layers run one by one."""
        kernels = kernels_for(self.inference_path, points, whole_network=True)
        if kernels is None or not len(points) or not out.is_contiguous() or out.dtype != torch.float32:
            return None
        weights = self.kernel_weights()
        if weights is None:
            return None
        point_index, local_segment = pairs
        counts = kernels.sorted_counts(segment.numpy(), b)
        local_counts = kernels.sorted_counts(local_segment.numpy(), b * NUM_REGIONS)
        if len(counts) != b or len(local_counts) != b * NUM_REGIONS:
            return None
        present = np.empty((b, NUM_REGIONS), np.bool_)
        work = kernels.work_memory(SCRATCH, "network",
                                   kernels.network_floats(weights, counts, local_counts, len(point_index)))
        kernels.pointpncnet_infer(as_numpy(points), counts, point_index.numpy(), local_counts, weights, out.numpy(),
                                  present, work)
        return torch.from_numpy(present)


@dataclass
class Packed:
    """A packed batch of clouds (see ``layers`` module doc)."""

    points: torch.Tensor  # (P, 3) float32
    segment: torch.Tensor  # (P,) int64
    regions: torch.Tensor | None  # (P, 8) bool; None when ``pairs`` is given
    batch_size: int
    #: (point index, instance * 8 + octant), sorted by the latter: ``regions`` as pairs (inference)
    pairs: tuple[torch.Tensor, torch.Tensor] | None = None

    def to(self, device: torch.device) -> Packed:
        return Packed(
            self.points.to(device, non_blocking=True),
            self.segment.to(device, non_blocking=True),
            None if self.regions is None else self.regions.to(device, non_blocking=True),
            self.batch_size,
            None if self.pairs is None else tuple(t.to(device, non_blocking=True) for t in self.pairs),
        )


def pack(
    clouds: Sequence[np.ndarray],
    overlap: float,
    regions: Sequence[np.ndarray] | None = None,
    pairs: bool = False,
) -> Packed:
    """Concatenate clouds into a :class:`Packed` batch (octant masks computed if not given).

    ``pairs``: give the octant memberships as sorted :func:`octant_pairs` instead of a mask
    (what inference uses; training keeps the mask).
    """
    lengths = np.fromiter((len(c) for c in clouds), dtype=np.int64, count=len(clouds))
    points = np.concatenate(clouds, axis=0).astype(np.float32, copy=False) if len(clouds) else np.zeros((0, 3))
    points = np.ascontiguousarray(points, dtype=np.float32)
    segment = torch.from_numpy(np.repeat(np.arange(len(clouds), dtype=np.int64), lengths))
    if pairs and regions is None:
        point_index, local = octant_pairs(points, lengths, overlap)
        return Packed(torch.from_numpy(points), segment, None, len(clouds),
                      (torch.from_numpy(point_index), torch.from_numpy(local)))
    masks = region_masks(points, overlap) if regions is None else np.concatenate(regions, axis=0)
    return Packed(torch.from_numpy(points), segment, torch.from_numpy(np.ascontiguousarray(masks, dtype=bool)),
                  len(clouds))
