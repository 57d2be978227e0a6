"""All completion metrics of one instance at once, in canonical units and in metres.

The evaluation computes every metric in the canonical car frame (the frame the backends
work in) and converts to metres with the instance's box length. Because the canonical
transform is rotation + translation + isotropic scale by ``1 / length``, a distance in
metres is exactly ``length`` x the canonical distance, and a squared distance
``length**2`` x. :data:`METRICS` records each metric's power of length, so the conversion
and the unit labels in tables cannot disagree.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pcc_ros.metrics.balance import far_completeness, lateral_offset
from pcc_ros.metrics.chamfer import PairDistances, chamfer_from_distances
from pcc_ros.metrics.emd import DEFAULT_MAX_POINTS, emd
from pcc_ros.metrics.fscore import fscore_from_distances, side_length
from pcc_ros.metrics.gtfree import fidelity, gt_free_metrics, side_view_cd


@dataclass(frozen=True)
class MetricInfo:
    """How a metric scales with length (0: dimensionless) and whether lower is better."""

    power: int
    lower_is_better: bool
    description: str


METRICS: dict[str, MetricInfo] = {
    "cd_l1": MetricInfo(1, True, "Chamfer L1: (precision + coverage) / 2, non-squared (PCN, PointPnCNet)"),
    "cd_l2": MetricInfo(2, True, "Chamfer L2: mean squared NN distance summed over both directions (PoinTr)"),
    "precision": MetricInfo(1, True, "mean distance prediction -> reference"),
    "coverage": MetricInfo(1, True, "mean distance reference -> prediction"),
    "fscore": MetricInfo(0, False, "F-score@1% (threshold 1% of the prediction's longest bbox side)"),
    "fscore_fixed": MetricInfo(0, False, "F-score at a fixed threshold in metres"),
    "emd": MetricInfo(1, True, "earth mover's distance, exact on <= 1024-point subsamples"),
    "fidelity": MetricInfo(2, True, "TraPCC L-I / MCD: mean squared distance input -> prediction"),
    "side_cd": MetricInfo(2, True, "TraPCC L-S: squared Chamfer of the side-view (x-z) projections"),
    "l_g": MetricInfo(2, True, "TraPCC L-G: squared Chamfer to the retrieved Whole-/Partial-GT (pseudo GT)"),
    "l_i": MetricInfo(2, True, "TraPCC L-I: MCD input -> prediction (= fidelity)"),
    "l_s": MetricInfo(2, True, "TraPCC L-S: side-view squared Chamfer to the retrieved Whole-GT"),
    "mean_cd": MetricInfo(2, True, "TraPCC meanCD: mean of L-G, L-I and L-S"),
    "far_coverage": MetricInfo(1, True, "coverage of the reference's half away from the sensor (the unseen half)"),
    "lateral_offset": MetricInfo(1, True, "lateral balance: |mean y| of the prediction (0: left/right balanced)"),
    "consistency": MetricInfo(1, True, "symmetric Chamfer-L1 between a track's predictions in consecutive frames"),
}


def unit_label(metric: str, metres: bool) -> str:
    """``m``, ``m^2``, ``canon``, ``canon^2`` or ``-`` for a dimensionless metric."""
    power = METRICS[metric].power
    if power == 0:
        return "-"
    base = "m" if metres else "canon"
    return base if power == 1 else f"{base}^{power}"


def to_metres(metric: str, value: float | np.ndarray, length: float | np.ndarray) -> float | np.ndarray:
    """Convert a canonical-unit value of ``metric`` to metres (``length`` = box length, m)."""
    return value * np.asarray(length, dtype=np.float64) ** METRICS[metric].power


def instance_metrics(
    pred: np.ndarray,
    reference: np.ndarray,
    partial: np.ndarray | None = None,
    *,
    length: float = 1.0,
    fixed_threshold_m: float = 0.05,
    with_emd: bool = True,
    emd_points: int = DEFAULT_MAX_POINTS,
    seed: int = 0,
    pseudo_gt: dict[str, np.ndarray | None] | None = None,
    origin: np.ndarray | None = None,
) -> dict[str, float]:
    """Every metric of one canonical (prediction, reference) pair, canonical units.

    ``reference`` is the ground-truth shape (SynthCars) or, without one, the multi-frame
    aggregated cloud of the track. ``partial`` (the network input) enables ``fidelity``;
    ``side_cd`` is always computed against ``reference``. ``length`` (metres) converts the
    fixed F-score threshold to canonical units. ``pseudo_gt`` (TraPCC's retrieved Whole- /
    Partial-GT, see :func:`~pcc_ros.metrics.gtfree.gt_free_metrics`) adds L-G, L-I, L-S and meanCD.
    ``origin`` (the sensor in the canonical frame) adds ``far_coverage``, the coverage of the
    reference's half away from the sensor (:mod:`pcc_ros.metrics.balance`); ``lateral_offset``
    is always computed; ``consistency`` spans two frames and is added by the evaluation.
    """
    if length <= 0 or not np.isfinite(length):
        raise ValueError(f"box length must be positive, got {length}")
    d = PairDistances.compute(pred, reference)
    out = chamfer_from_distances(d)
    out["fscore"] = fscore_from_distances(d, 0.01 * side_length(pred))["fscore"]
    out["fscore_fixed"] = fscore_from_distances(d, fixed_threshold_m / length)["fscore"]
    if with_emd:
        out["emd"] = emd(pred, reference, max_points=emd_points, seed=seed)
    if partial is not None:
        out["fidelity"] = fidelity(partial, pred)
    out["side_cd"] = side_view_cd(pred, reference)
    out["lateral_offset"] = lateral_offset(pred)
    if origin is not None:
        out["far_coverage"] = far_completeness(reference, pred, origin)
    if pseudo_gt is not None and partial is not None:
        out.update(gt_free_metrics(pred, partial, pseudo_gt))
    return out
