"""Shared torch building blocks for the completion backends.

Point clouds of real cars have very different sizes (a distant car has 30 points, a close
one 3000). Resampling every cloud to a fixed size wastes most of the compute on duplicates,
so the encoders here work on a *packed* batch: all points of all instances concatenated
into one ``(P, 3)`` tensor plus a ``(P,)`` segment id saying which instance (or which
instance-and-region) each point belongs to. Max-pooling is a segment-wise max (segments sorted), so
the cost is proportional to the real number of points.

The PCN-style encoder and the folding decoder below are algebraically the published
architectures; where a layer is applied to a concatenation ``[per-point ; per-segment]``
it is split into two linear maps (``W [a; b] = W_a a + W_b b``) so the per-segment half is
computed once per segment instead of once per point. That is the same function with the
same parameters count, only cheaper — it is what makes the folding decoder affordable on
a CPU.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn


def segment_max(features: torch.Tensor, segment: torch.Tensor, num_segments: int) -> torch.Tensor:
    """Channel-wise max of ``features`` ``(P, C)`` per segment id ``(P,)`` -> ``(S, C)``.

    ``segment`` must be sorted (non-decreasing), which packing gives for free; then a
    ``segment_reduce`` over run lengths is several times cheaper (forward and backward)
    than a scatter max. Empty segments come out as zeros; callers mask them.
    """
    lengths = torch.bincount(segment, minlength=num_segments)
    if features.shape[0] == 0:
        return features.new_zeros(num_segments, features.shape[1])
    out = torch.segment_reduce(features, "max", lengths=lengths, unsafe=True)
    return torch.where((lengths > 0)[:, None], out, torch.zeros_like(out))


class SharedMLP(nn.Module):
    """Point-wise MLP (the 1x1 convolution of PointNet/PCN) over the last dimension.

    ReLU between layers; the last layer is linear unless ``final_relu``.
    """

    def __init__(self, in_dim: int, widths: Sequence[int], final_relu: bool = False) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        last = in_dim
        for i, w in enumerate(widths):
            layers.append(nn.Linear(last, w))
            if i < len(widths) - 1 or final_relu:
                layers.append(nn.ReLU(inplace=True))
            last = w
        self.net = nn.Sequential(*layers)
        self.out_dim = last

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)


class PCNEncoder(nn.Module):
    """PCN encoder on a packed batch.

    ``mlp1`` (3 -> widths1) per point, max-pool per segment, concatenate the pooled feature
    to every point of its segment, ``mlp2`` (2*widths1[-1] -> widths2) per point, max-pool.
    The first layer of ``mlp2`` is split into a point part and a segment part (see module doc).
    """

    def __init__(self, widths1: Sequence[int], widths2: Sequence[int]) -> None:
        super().__init__()
        if len(widths2) < 1:
            raise ValueError("widths2 needs at least one layer")
        self.mlp1 = SharedMLP(3, widths1)
        c1 = self.mlp1.out_dim
        self.point_proj = nn.Linear(c1, widths2[0])
        self.segment_proj = nn.Linear(c1, widths2[0], bias=False)
        self.mlp2 = SharedMLP(widths2[0], widths2[1:]) if len(widths2) > 1 else None
        self.out_dim = widths2[-1]
        self._single = len(widths2) == 1

    def forward(self, points: torch.Tensor, segment: torch.Tensor, num_segments: int) -> torch.Tensor:
        """``points`` ``(P, 3)``, ``segment`` ``(P,)`` in ``[0, num_segments)`` -> ``(S, out_dim)``."""
        f = self.mlp1(points)
        g = segment_max(f, segment, num_segments)
        h = self.point_proj(f) + self.segment_proj(g)[segment]
        if not self._single:
            h = self.mlp2(torch.relu(h))
        return segment_max(h, segment, num_segments)


def folding_grid(size: int, scale: float) -> torch.Tensor:
    """``(size*size, 2)`` regular 2-D grid in ``[-scale, scale]^2`` (a single point at 0 for size 1)."""
    if size == 1:
        return torch.zeros(1, 2)
    t = torch.linspace(-scale, scale, size)
    gx, gy = torch.meshgrid(t, t, indexing="ij")
    return torch.stack([gx.reshape(-1), gy.reshape(-1)], dim=1)


class FoldingDecoder(nn.Module):
    """PCN decoder: fully connected layers to ``num_coarse`` points, then one folding step.

    Each coarse point is expanded into ``grid_size**2`` points by an MLP over
    ``[grid coordinate ; coarse point ; code]``, whose output is added to the coarse point
    (residual). The first folding layer is split so the code part is computed once per
    segment (the reason the published decoder over 1029-wide features is affordable here).
    Output: ``num_coarse * grid_size**2`` points.
    """

    def __init__(
        self,
        code_dim: int,
        fc_widths: Sequence[int],
        num_coarse: int,
        grid_size: int,
        fold_widths: Sequence[int],
        grid_scale: float,
    ) -> None:
        super().__init__()
        if len(fold_widths) < 1:
            raise ValueError("fold_widths needs at least one hidden layer")
        self.num_coarse = num_coarse
        self.fc = SharedMLP(code_dim, [*fc_widths, num_coarse * 3])
        self.register_buffer("grid", folding_grid(grid_size, grid_scale), persistent=False)
        h = fold_widths[0]
        self.fold_code = nn.Linear(code_dim, h)
        self.fold_point = nn.Linear(3, h, bias=False)
        self.fold_grid = nn.Linear(2, h, bias=False)
        self.fold_mlp = SharedMLP(h, [*fold_widths[1:], 3])
        self.num_points = num_coarse * self.grid.shape[0]

    def forward(self, code: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``code`` ``(S, code_dim)`` -> ``(coarse (S, K, 3), fine (S, K*G, 3))``."""
        s = code.shape[0]
        coarse = self.fc(code).view(s, self.num_coarse, 3)
        h = (
            self.fold_code(code)[:, None, None, :]
            + self.fold_point(coarse)[:, :, None, :]
            + self.fold_grid(self.grid)[None, None, :, :]
        )
        offset = self.fold_mlp(torch.relu(h))
        fine = (coarse[:, :, None, :] + offset).reshape(s, -1, 3)
        return coarse, fine


# --------------------------------------------------------------------------- losses

_EPS = 1e-9


def _nearest(query: torch.Tensor, ref: torch.Tensor, ref_mask: torch.Tensor | None = None) -> torch.Tensor:
    """Index ``(..., M)`` of the nearest valid ``ref`` ``(..., N, 3)`` point of each ``query`` ``(..., M, 3)``.

    ``argmin_n |q - r_n|^2 = argmin_n (|r_n|^2 - 2 q.r_n)``: the query's own norm is constant
    along the row, so one fused ``baddbmm`` gives the ranking; invalid references get an
    infinite norm instead of a masked copy of the big matrix.
    """
    lead = query.shape[:-2]
    q = query.reshape(-1, *query.shape[-2:])
    r = ref.reshape(-1, *ref.shape[-2:])
    rr = (r * r).sum(-1)
    if ref_mask is not None:
        rr = rr.masked_fill(~ref_mask.reshape(rr.shape), float("inf"))
    score = torch.baddbmm(rr[:, None, :], q, r.transpose(1, 2), alpha=-2.0)
    return score.argmin(-1).reshape(*lead, query.shape[-2])


def weighted_chamfer(
    target: torch.Tensor,
    target_mask: torch.Tensor,
    pred: torch.Tensor,
    beta: float,
) -> torch.Tensor:
    """Asymmetric weighted Chamfer distance (PointPnCNet Eq. 1), one value per row.

    ``(1 - beta) * mean_{x in X} min_y |x - y| + beta * mean_{y in Y} min_x |y - x|`` with
    ``X`` = ``target`` ``(..., N, 3)`` valid where ``target_mask`` ``(..., N)`` (targets are
    observed partial clouds of different sizes, so they come padded) and ``Y`` = ``pred``
    ``(..., M, 3)``. Distances are Euclidean, not squared (PCN's and the paper's Chamfer-L1);
    the square root is taken after the minimum, with a small epsilon, so the gradient stays
    finite when a prediction sits exactly on a target point. Rows with an empty target
    give 0; callers leave them out of their averages.
    """
    # Nearest neighbours without autograd (the (M, N) matrix is the expensive part and its
    # backward would be as big), then the distances of the chosen pairs with autograd: the
    # gradient is exactly that of the min formulation, at a fraction of the memory.
    with torch.no_grad():
        nn_y2x = _nearest(pred, target, target_mask)  # (..., M) nearest valid target point
        nn_x2y = _nearest(target, pred)  # (..., N) nearest prediction of each target point
    near_x = torch.gather(target, -2, nn_y2x[..., None].expand(*nn_y2x.shape, 3))
    near_y = torch.gather(pred, -2, nn_x2y[..., None].expand(*nn_x2y.shape, 3))
    y2x = torch.sqrt(((pred - near_x) ** 2).sum(-1) + _EPS)
    x2y = torch.sqrt(((target - near_y) ** 2).sum(-1) + _EPS)
    tmask = target_mask.to(pred.dtype)
    n_x = tmask.sum(-1)
    x_term = (x2y * tmask).sum(-1) / n_x.clamp_min(1.0)
    loss = (1.0 - beta) * x_term + beta * y2x.mean(-1)
    return torch.where(n_x > 0, loss, torch.zeros_like(loss))


def masked_mean(values: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean of ``values`` where ``mask``; 0 (still differentiable) when nothing is selected."""
    m = mask.to(values.dtype)
    return (values * m).sum() / m.sum().clamp_min(1.0)
