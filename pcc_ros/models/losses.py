"""Training losses of the completion networks: the asymmetric weighted Chamfer distance
(PointPnCNet's Eq. 1, TraPCC's terms) on padded batches, the left / right symmetry term, and the
masked mean they average with."""

from __future__ import annotations

import torch

_EPS = 1e-9


def nearest(query: torch.Tensor, ref: torch.Tensor, ref_mask: torch.Tensor | None = None) -> torch.Tensor:
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
        nn_y2x = nearest(pred, target, target_mask)  # (..., M) nearest valid target point
        nn_x2y = nearest(target, pred)  # (..., N) nearest prediction of each target point
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


def reflect_y(points: torch.Tensor) -> torch.Tensor:
    """``points`` ``(..., 3)`` reflected across the box's x-z plane (``y -> -y``)."""
    return points * torch.tensor([1.0, -1.0, 1.0], dtype=points.dtype, device=points.device)


def reflect(points: torch.Tensor, reflection: torch.Tensor | None = None) -> torch.Tensor:
    """``points`` ``(B, ..., 3)`` reflected across the box's x-z plane (``reflection`` ``None``) or,
    row ``b`` of the batch, by the ``(3, 4)`` affine map ``reflection[b]`` (its car's plane)."""
    if reflection is None:
        return reflect_y(points)
    r = reflection.to(points.dtype)
    flat = points.reshape(points.shape[0], -1, 3)
    return (flat @ r[:, :, :3].transpose(1, 2) + r[:, None, :, 3]).reshape(points.shape)


def symmetry_chamfer(points: torch.Tensor, reflection: torch.Tensor | None = None) -> torch.Tensor:
    """Mean over rows of the symmetric Chamfer-L1 between ``points`` ``(B, M, 3)`` and their
    reflection across the box's x-z plane (or across each row's plane, the ``(B, 3, 4)`` affine
    maps ``reflection``): 0 for a left / right symmetric shape. A car is symmetric, and no
    self-supervised target asks for the flank the sensor did not see."""
    reflected = reflect(points, reflection)
    full = torch.ones(reflected.shape[:-1], dtype=torch.bool, device=reflected.device)
    return weighted_chamfer(reflected, full, points, 0.5).mean()


def symmetry_density(points: torch.Tensor, reflection: torch.Tensor | None = None) -> torch.Tensor:
    """Mean over rows of the 1-D Wasserstein distance between the lateral (y) coordinates of ``points``
    ``(B, M, 3)`` and those of their reflection (the planes of :func:`symmetry_chamfer`): 0 when as many
    points lie at each distance on one flank as on the other.

    Why beside :func:`symmetry_chamfer`: a Chamfer distance ignores how many points lie where, so an
    output that draws both flanks but puts most of its points on one meets it. TraPCC's shipped weights
    do that: symmetric lateral extents, most points on the car's +y side whichever flank was seen
    (``docs/trapcc.md``, far side), which ``pcc eval``'s lateral balance reads as a lean.
    """
    lateral = points[..., 1].sort(-1).values
    mirrored = reflect(points, reflection)[..., 1].sort(-1).values
    return (lateral - mirrored).abs().mean()
