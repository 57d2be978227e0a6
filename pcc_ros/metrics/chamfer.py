"""Chamfer distance in its two common forms, with its one-sided parts.

Conventions (the literature mixes them, so every number states which it is):

* ``precision`` = mean over *predicted* points of the distance to the nearest true point
  (are the predicted points on the shape?); ``coverage`` = mean over *true* points of the
  distance to the nearest predicted point (is all of the shape predicted?). Distances are
  Euclidean, not squared. This is the split of Gu et al., reported by PointPnCNet.
* ``cd_l1`` = (precision + coverage) / 2: mean of non-squared nearest-neighbour distances,
  averaged over both directions (PCN; PointPnCNet's Eq. 1 with beta = 0.5). Unit: length.
* ``cd_l2`` = mean squared distance prediction -> truth + mean squared distance
  truth -> prediction, *summed* (PoinTr, TraPCC Eq. 1). Unit: length squared.

Nearest neighbours come from ``scipy.spatial.cKDTree`` (C, O(N log N)), never a Python
loop over points. All functions work in whatever unit the clouds are in; the evaluation
runs them in the canonical frame and scales by the box length (squared for ``cd_l2``) to
metres, which is exact because the canonical transform is a rigid motion plus an isotropic
scale.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree


def _as_cloud(cloud: np.ndarray, what: str) -> np.ndarray:
    array = np.asarray(cloud, dtype=np.float64)
    if array.ndim != 2 or array.shape[1] not in (2, 3) or len(array) == 0:
        raise ValueError(f"{what}: expected a non-empty (N, 2|3) cloud, got shape {array.shape}")
    return array


def nearest_distances(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """``(N,)`` Euclidean distance from each source point to its nearest target point."""
    source = _as_cloud(source, "source")
    target = _as_cloud(target, "target")
    if source.shape[1] != target.shape[1]:
        raise ValueError(f"dimension mismatch: source {source.shape[1]}-D, target {target.shape[1]}-D")
    distances, _ = cKDTree(target).query(source, k=1)
    return np.asarray(distances, dtype=np.float64)


def nearest_distances_batch(
    sources: Sequence[np.ndarray], targets: Sequence[np.ndarray], spacing: float = 1e4
) -> list[np.ndarray]:
    """Per pair ``k``, the distance from each point of ``sources[k]`` to its nearest point of
    ``targets[k]`` — all pairs in one KD-tree build and one query.

    Pair ``k`` is shifted by ``k * spacing`` along x, far beyond the extent of any cloud
    (checked), so no nearest neighbour can cross pairs. Much faster than a tree per pair
    for the many small clouds of one LiDAR frame.
    """
    if len(sources) != len(targets):
        raise ValueError(f"{len(sources)} sources for {len(targets)} targets")
    if not sources:
        return []
    src = [_as_cloud(s, f"source {k}") for k, s in enumerate(sources)]
    tgt = [_as_cloud(t, f"target {k}") for k, t in enumerate(targets)]
    extent = max(float(np.abs(c).max()) for c in (*src, *tgt))
    if not np.isfinite(extent) or extent * 4 >= spacing:
        raise ValueError(f"clouds span {extent}: not finite or too large for spacing {spacing}")
    src_owner = np.repeat(np.arange(len(src)), [len(s) for s in src])
    tgt_owner = np.repeat(np.arange(len(tgt)), [len(t) for t in tgt])
    src_all, tgt_all = np.concatenate(src), np.concatenate(tgt)
    src_all[:, 0] += src_owner * spacing
    tgt_all[:, 0] += tgt_owner * spacing
    distances, _ = cKDTree(tgt_all, balanced_tree=False, compact_nodes=False).query(src_all, k=1)
    return np.split(np.asarray(distances, dtype=np.float64), np.cumsum([len(s) for s in src])[:-1])


@dataclass(frozen=True)
class PairDistances:
    """Both directions' nearest-neighbour distances of a (prediction, truth) pair.

    Computed once and shared by Chamfer and F-score so each pair is queried only twice.
    """

    pred_to_truth: np.ndarray
    truth_to_pred: np.ndarray

    @classmethod
    def compute(cls, pred: np.ndarray, truth: np.ndarray) -> PairDistances:
        return cls(nearest_distances(pred, truth), nearest_distances(truth, pred))


def chamfer_from_distances(d: PairDistances) -> dict[str, float]:
    """Chamfer figures (see module docstring) from precomputed distances."""
    precision = float(d.pred_to_truth.mean())
    coverage = float(d.truth_to_pred.mean())
    precision_l2 = float(np.square(d.pred_to_truth).mean())
    coverage_l2 = float(np.square(d.truth_to_pred).mean())
    return {
        "cd_l1": 0.5 * (precision + coverage),
        "cd_l2": precision_l2 + coverage_l2,
        "precision": precision,
        "coverage": coverage,
        "precision_l2": precision_l2,
        "coverage_l2": coverage_l2,
    }


def chamfer(pred: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    """``cd_l1``, ``cd_l2``, ``precision``, ``coverage`` (+ squared one-sided parts) of one pair."""
    return chamfer_from_distances(PairDistances.compute(pred, truth))


def chamfer_l1(pred: np.ndarray, truth: np.ndarray) -> float:
    """PCN / PointPnCNet Chamfer: mean non-squared NN distance, averaged over both directions."""
    return chamfer(pred, truth)["cd_l1"]


def chamfer_l2(pred: np.ndarray, truth: np.ndarray) -> float:
    """PoinTr Chamfer: mean squared NN distance, summed over both directions."""
    return chamfer(pred, truth)["cd_l2"]


def one_sided(source: np.ndarray, target: np.ndarray, squared: bool = False) -> float:
    """Mean (squared if ``squared``) distance from each source point to the target cloud."""
    d = nearest_distances(source, target)
    return float(np.square(d).mean() if squared else d.mean())


def chamfer_batch(preds: Sequence[np.ndarray], truths: Sequence[np.ndarray]) -> dict[str, np.ndarray]:
    """:func:`chamfer` over a batch of pairs; each key maps to a ``(B,)`` array."""
    if len(preds) != len(truths):
        raise ValueError(f"{len(preds)} predictions for {len(truths)} truths")
    rows = [chamfer(p, t) for p, t in zip(preds, truths)]  # loop over instances; each pair is vectorised
    keys = ("cd_l1", "cd_l2", "precision", "coverage", "precision_l2", "coverage_l2")
    return {k: np.array([r[k] for r in rows], dtype=np.float64) for k in keys}
