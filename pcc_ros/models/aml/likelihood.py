"""AML's likelihoods: the observed-voxel NLL (Eq. 4/5 data term) and the reference NLL (Eq. 2)."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F


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
