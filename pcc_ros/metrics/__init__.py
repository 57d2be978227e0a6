"""Completion metrics (CPU, NumPy/SciPy): Chamfer L1/L2 with precision and coverage,
F-score, exact EMD on subsamples, and TraPCC's ground-truth-free fidelity and side-view CD.

Conventions are stated in each module's docstring and in ``docs/evaluation.md``.
"""

from pcc_ros.metrics.chamfer import (
    PairDistances,
    chamfer,
    chamfer_batch,
    chamfer_l1,
    chamfer_l2,
    nearest_distances,
    one_sided,
)
from pcc_ros.metrics.emd import emd, emd_exact
from pcc_ros.metrics.fscore import fscore, fscore_at_percent, percent_threshold, side_length
from pcc_ros.metrics.gtfree import fidelity, side_view_cd
from pcc_ros.metrics.suite import METRICS, instance_metrics, to_metres, unit_label

__all__ = [
    "METRICS",
    "PairDistances",
    "chamfer",
    "chamfer_batch",
    "chamfer_l1",
    "chamfer_l2",
    "emd",
    "emd_exact",
    "fidelity",
    "fscore",
    "fscore_at_percent",
    "instance_metrics",
    "nearest_distances",
    "one_sided",
    "percent_threshold",
    "side_length",
    "side_view_cd",
    "to_metres",
    "unit_label",
]
