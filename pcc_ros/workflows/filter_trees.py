"""``pcc calibrate-filter --trees-out FILE``: boost trees from a weighted sum, and say what they add.

The evidence rule's weighted sum (:mod:`pcc_ros.workflows.filter_sensors`) keeps the false boxes
that read like a car on each term alone: vegetation blobs, bins, low walls boxed as cars, boxes
pushed off their car into its shadow. Trees over the same terms, boosted from the sum's logit
(:func:`pcc_ros.workflows.boosting.boost`), can say "this term matters when that one is high". This
module fits them on the calibration rows -- every simulated layout's and the real frames', each
layout and the real frames weighing the same, as the sum was fitted -- and reports, held out:

* **by sequence** (fold ``k`` holds out the ``k``-th sequence of every layout and the ``k``-th block
  of real frames; trees refit on the rest, the sum kept): per kind, AUC and the share removed at
  the best threshold for <= 2 % of the true cars lost, with and without the trees;
* **real frames** (blocks of neighbouring frames held out in turn, trees boosted without the block):
  the block judged at its beam layout's threshold.

Each layout's threshold is then set by the per-layout cross-validation of
:mod:`pcc_ros.workflows.sensor_thresholds` on the *out-of-fold* p_false of the by-sequence folds:
300 trees fit their own rows, and thresholds set on in-sample p_false lost 15-25 % more true cars
than their budget on held-out sequences (docs/filter_history.md, *Boosted trees*).
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from pcc_ros.pipeline.filter import TERMS, FilterConfig
from pcc_ros.pipeline.trees import TermTrees
from pcc_ros.workflows.boosting import boost
from pcc_ros.workflows.filter_sensors import Rows, figures, filled, rows_probability, sensor_balance

#: Terms the trees may split on by default: every measured term but the detector score (an unknown
#: detector's scale is unknown) and the shape mismatch (a completion of every box).
TREE_TERMS = tuple(t for t in TERMS if t not in ("score", "mismatch"))
#: The direction of the terms whose physics gives one (+1: a larger value says "false"), as the
#: shipped weights' signs do; ``--tree-monotone`` keeps the trees from bending against them.
PHYSICAL_DIRECTION = {"density": -1, "free_space": 1, "ground_gap": 1, "above": 1, "overlap": 1, "depth": 1,
                      "corner": -1, "cover": -1, "through": 1}


def boost_rows(rows: Rows, config: FilterConfig, terms: tuple[str, ...] = TREE_TERMS, depth: int = 3,
               rounds: int = 300, rate: float = 0.05, monotone: bool = False) -> TermTrees:
    """Trees over ``terms`` boosted from the logit of ``config``'s weighted sum (its own trees left
    out), on ``rows``, every sensor (and the real frames) weighing the same; ``monotone``: each term of
    :data:`PHYSICAL_DIRECTION` held to its direction."""
    p = np.clip(rows_probability(rows, config, None), 1e-12, 1 - 1e-12)
    cols = [TERMS.index(t) for t in terms]
    signs = tuple(PHYSICAL_DIRECTION.get(t, 0) for t in terms) if monotone else None
    trees = boost(filled(rows.x, config.mismatch_mean)[:, cols], rows.false, sensor_balance(rows), np.log(p / (1 - p)),
                  terms, depth=depth, rounds=rounds, rate=rate, monotone=signs)
    linear = {"w_bias": float(config.w_bias), **{f"w_{t}": float(w) for t, w in zip(TERMS, config.weights)}}
    return replace(trees, linear=linear)


def _sequence_folds(rows: Rows) -> np.ndarray:
    """Fold of each row: the rank of its group among its sensor's groups (sorted names)."""
    fold = np.zeros(len(rows.false), dtype=np.int64)
    for s in np.unique(rows.sensor):
        sel = rows.sensor == s
        _, fold[sel] = np.unique(rows.group[sel], return_inverse=True)
    return fold


def held_out_by_sequence(rows: Rows, config: FilterConfig, **settings) -> tuple[dict[str, Any], np.ndarray]:
    """Fold ``k``: the ``k``-th sequence of every layout (and block of real frames) held out, trees
    boosted on the rest. Returns the pooled figures against the weighted sum alone, and every row's
    out-of-fold p_false (what the thresholds are set on: trees fit their own rows, so in-sample
    p_false would set thresholds that lose more than the budget on data they never saw)."""
    fold = _sequence_folds(rows)
    p = np.zeros(len(rows.false))
    for k in np.unique(fold):
        test = fold == k
        trees = boost_rows(rows.subset(~test), config, **settings)
        p[test] = rows_probability(rows.subset(test), config, trees)
    report = {"folds": int(fold.max()) + 1, "with_trees": _ranking(p, rows),
              "sum_alone": _ranking(rows_probability(rows, config, None), rows)}
    return report, p


def _ranking(p: np.ndarray, rows: Rows) -> dict[str, Any]:
    """:func:`figures` without a threshold (no decision is made here): the AUC and the best removal
    at <= 2 % lost, and per kind its count and AUC."""
    fig = figures(p, rows, np.zeros(len(p), bool))
    del fig["true_lost"], fig["false_removed"]
    fig["per_kind"] = {k: {"count": v["count"], "auc_vs_true": v["auc_vs_true"]} for k, v in fig["per_kind"].items()}
    return fig


def held_out_real(rows: Rows, config: FilterConfig, threshold: float, **settings) -> dict[str, Any]:
    """Each block of real frames held out in turn, trees boosted without it, the block judged at
    ``threshold`` (its layout's, from the out-of-fold p_false)."""
    real = rows.sensor == "real"
    p = np.zeros(len(rows.false))
    for g in np.unique(rows.group[real]):
        test = rows.group == g
        p[test] = rows_probability(rows.subset(test), config, boost_rows(rows.subset(~test), config, **settings))
    return {"threshold": threshold, **figures(p[real], rows.subset(real), p[real] > threshold)}
