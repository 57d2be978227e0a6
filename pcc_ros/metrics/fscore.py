"""F-score at a distance threshold (Tatarchenko et al.; "F-score@1%" of GRNet / PointPnCNet).

``precision(d)`` = fraction of predicted points within ``d`` of the truth, ``recall(d)`` =
fraction of true points within ``d`` of the prediction, ``F = 2 P R / (P + R)`` (0 when both
are 0). A point exactly at distance ``d`` counts as matched (``<=``).

Threshold conventions:

* ``@1%`` (PointPnCNet supplementary 7.4.2, following Xie et al.): ``d = 1%`` of the *side
  length of the predicted cloud*, defined here precisely as the longest side of the
  prediction's axis-aligned bounding box (in the canonical frame the car's x extent, about
  1 canonical unit, so ``d`` is about 0.01, i.e. about 4.5 cm on a 4.5 m car). Because it
  follows the paper, a prediction that is too small is also judged with a stricter threshold;
  ``reference="truth"`` uses the ground truth's box instead, identical for every backend.
* a fixed threshold in metres (:func:`fscore` with ``threshold`` = metres / box length in
  canonical units), comparable across objects of different size.

F-score is dimensionless, so it is the same in metres and canonical units when the
threshold is converted with the same box length.
"""

from __future__ import annotations

import numpy as np

from pcc_ros.metrics.chamfer import PairDistances


def side_length(cloud: np.ndarray) -> float:
    """Longest side of the cloud's axis-aligned bounding box."""
    array = np.asarray(cloud, dtype=np.float64)
    if array.ndim != 2 or len(array) == 0:
        raise ValueError(f"side_length: expected a non-empty (N, D) cloud, got {array.shape}")
    return float((array.max(axis=0) - array.min(axis=0)).max())


def fscore_from_distances(d: PairDistances, threshold: float) -> dict[str, float]:
    """``fscore``, ``fscore_precision``, ``fscore_recall`` at ``threshold`` from precomputed distances."""
    if not np.isfinite(threshold) or threshold < 0:
        raise ValueError(f"F-score threshold must be finite and >= 0, got {threshold}")
    precision = float(np.mean(d.pred_to_truth <= threshold))
    recall = float(np.mean(d.truth_to_pred <= threshold))
    f = 0.0 if precision + recall == 0 else 2.0 * precision * recall / (precision + recall)
    return {"fscore": f, "fscore_precision": precision, "fscore_recall": recall}


def fscore(pred: np.ndarray, truth: np.ndarray, threshold: float) -> float:
    """F-score of one pair at an absolute ``threshold`` (same unit as the clouds)."""
    return fscore_from_distances(PairDistances.compute(pred, truth), threshold)["fscore"]


def percent_threshold(
    pred: np.ndarray, truth: np.ndarray, percent: float = 1.0, reference: str = "prediction"
) -> float:
    """``percent`` % of the longest bounding-box side of the prediction (paper) or the truth."""
    if reference == "prediction":
        return percent / 100.0 * side_length(pred)
    if reference == "truth":
        return percent / 100.0 * side_length(truth)
    raise ValueError(f"reference must be 'prediction' or 'truth', got {reference!r}")


def fscore_at_percent(
    pred: np.ndarray, truth: np.ndarray, percent: float = 1.0, reference: str = "prediction"
) -> float:
    """F-score@``percent``% (default: the PointPnCNet / GRNet F-score@1%)."""
    return fscore(pred, truth, percent_threshold(pred, truth, percent, reference))
