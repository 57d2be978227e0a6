"""Boosted trees over the evidence terms: what a weighted sum of the terms cannot say.

The evidence rule's logit is a weighted sum of terms (:mod:`pcc_ros.pipeline.filter`). A sum
cannot say "deep returns matter when the box is dense, not when it holds three returns", and the
false boxes a sum keeps are of that sort: a vegetation blob or a bin reads like a car on each term
alone and unlike one on two together. :class:`TermTrees` adds to that logit the leaves of shallow
regression trees over the same terms, boosted from the weighted sum on the calibration rows
(:func:`pcc_ros.workflows.boosting.boost`):

    p_false = sigmoid(w_bias + sum_k w_k * term_k + sum_t leaf_t(terms))

The trees are stored complete, in heap order (node ``i``'s children are ``2i+1`` and ``2i+2``);
a node that did not split sends every box left (threshold ``+inf``, ``null`` in the file). A box
goes right where ``term > threshold``; a missing term reads 0 as in the weighted sum
(:func:`pcc_ros.pipeline.filter.term_matrix`). Evaluating ``T`` trees of depth ``D`` on ``N``
boxes is ``D`` gathers over an ``(N, T)`` array: no loop over boxes or trees.

A file of trees belongs to the weighted sum it was boosted from: it records those weights, and
the filter refuses to add it to others (:meth:`TermTrees.check_linear`).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pcc_ros.errors import ConfigError

#: ``format`` of a trees file; a reader refuses any other.
FORMAT = "pcc_ros.filter_trees/1"
#: ``trees:`` value naming the file shipped in ``pcc_ros/weights`` (the default rule's).
SHIPPED = "shipped"
SHIPPED_PATH = Path(__file__).resolve().parents[1] / "weights" / "filter_trees.json"
#: Largest difference between a file's recorded weights and a rule's that still counts as the
#: same weighted sum (the node YAML keeps 4 decimals).
WEIGHT_TOLERANCE = 5e-4


@dataclass(frozen=True)
class TermTrees:
    """``T`` complete trees of depth ``D`` over the named ``terms``.

    ``feature (T, 2**D - 1)``: the column of ``terms`` each inner node tests; ``threshold (T, 2**D - 1)``:
    a box goes right where its term exceeds it (``inf``: never); ``leaf (T, 2**D)``: the logit each
    leaf adds. ``linear``: the weighted sum (``w_bias`` and every ``w_<term>``) they were boosted
    from; ``provenance``: how they were fitted (data, settings, figures)."""

    terms: tuple[str, ...]
    feature: np.ndarray
    threshold: np.ndarray
    leaf: np.ndarray
    linear: dict[str, float] = field(default_factory=dict)
    provenance: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        t, inner = self.feature.shape
        depth = round(math.log2(inner + 1))
        if (self.threshold.shape != (t, inner) or self.leaf.shape != (t, inner + 1) or 2 ** depth - 1 != inner
                or not len(self.terms)):
            raise ValueError(f"trees: feature {self.feature.shape}, threshold {self.threshold.shape} and leaf "
                             f"{self.leaf.shape} are not {t} complete trees over {len(self.terms)} terms")
        if t and (self.feature.min() < 0 or self.feature.max() >= len(self.terms)):
            raise ValueError(f"trees: a node tests a column outside the {len(self.terms)} terms")
        if not np.isfinite(self.leaf).all() or np.isnan(self.threshold).any():
            raise ValueError("trees: a leaf is not finite or a threshold is NaN")

    @property
    def depth(self) -> int:
        return round(math.log2(self.feature.shape[1] + 1))

    def margin(self, x: np.ndarray) -> np.ndarray:
        """The logit the trees add for each row of ``x (N, len(terms))`` (missing terms as 0)."""
        x = np.nan_to_num(np.asarray(x, dtype=np.float64), nan=0.0)
        n, t = len(x), len(self.leaf)
        if not n or not t:
            return np.zeros(n)
        tree = np.arange(t)[None, :]
        node = np.zeros((n, t), dtype=np.int64)
        rows = np.arange(n)[:, None]
        for _ in range(self.depth):
            value = x[rows, self.feature[tree, node]]
            node = 2 * node + 1 + (value > self.threshold[tree, node])
        return self.leaf[tree, node - self.feature.shape[1]].sum(axis=1)

    def check_linear(self, weights: dict[str, float], source: str) -> None:
        """Refuse to add these trees to a weighted sum other than the one they were boosted from
        (``weights``: ``w_bias`` and the ``w_<term>`` of the rule in force)."""
        off = {k: (v, weights.get(k, 0.0)) for k, v in self.linear.items()
               if abs(v - weights.get(k, 0.0)) > WEIGHT_TOLERANCE}
        if off:
            said = ", ".join(f"{k} {a:g} (rule: {b:g})" for k, (a, b) in sorted(off.items()))
            raise ConfigError(f"{source}: these trees were boosted from other filter weights ({said}); a calibrated "
                              "rule is a whole: use the trees pcc calibrate-filter wrote beside these weights, or "
                              "trees: \"\" for the weighted sum alone")

    def to_json(self) -> dict[str, Any]:
        return {"format": FORMAT, "terms": list(self.terms), "depth": self.depth,
                "feature": self.feature.tolist(),
                "threshold": [[None if math.isinf(v) else float(v) for v in row] for row in self.threshold],
                "leaf": self.leaf.tolist(), "linear": self.linear, "provenance": self.provenance}

    def save(self, path: Path) -> None:
        """Write atomically (a file beside, then renamed): a reader never sees half a file. One
        tree a line, so that a diff of two calibrations reads tree by tree."""
        doc = self.to_json()
        body = []
        for key, value in doc.items():
            if key in ("feature", "threshold", "leaf"):
                rows = ",\n".join("  " + json.dumps(row) for row in value)
                body.append(f" {json.dumps(key)}: [\n{rows}\n ]")
            else:
                body.append(f" {json.dumps(key)}: {json.dumps(value)}")
        path = Path(path)
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_text("{\n" + ",\n".join(body) + "\n}\n")
        tmp.replace(path)


def load_trees(path: str | Path, known_terms: tuple[str, ...]) -> TermTrees:
    """Read a trees file; :class:`ConfigError` naming the file for anything but a valid one over
    ``known_terms`` (a truncated file, another format, an unknown term, a malformed tree)."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, RecursionError, json.JSONDecodeError) as exc:
        raise ConfigError(f"{path}: not a readable filter trees file ({exc})") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise ConfigError(f"{path}: not a filter trees file (format {FORMAT!r} expected)")
    try:
        terms = tuple(str(t) for t in doc["terms"])
        unknown = sorted(set(terms) - set(known_terms))
        if unknown:
            raise ConfigError(f"{path}: unknown evidence terms {unknown} (have {', '.join(known_terms)})")
        threshold = np.array([[np.inf if v is None else v for v in row] for row in doc["threshold"]], dtype=np.float64)
        trees = TermTrees(terms, np.asarray(doc["feature"], dtype=np.int64).reshape(len(threshold), -1),
                          threshold.reshape(len(threshold), -1),
                          np.asarray(doc["leaf"], dtype=np.float64).reshape(len(threshold), -1),
                          {str(k): float(v) for k, v in doc.get("linear", {}).items()}, dict(doc.get("provenance", {})))
    except (AttributeError, KeyError, TypeError, ValueError) as exc:
        raise ConfigError(f"{path}: malformed filter trees ({exc})") from None
    if trees.depth != doc.get("depth"):
        raise ConfigError(f"{path}: malformed filter trees (depth {doc.get('depth')} recorded, {trees.depth} stored)")
    return trees


def trees_path(value: str) -> Path | None:
    """The file a ``trees`` parameter names: ``shipped`` the packaged one, ``""`` none."""
    if not value:
        return None
    return SHIPPED_PATH if value == SHIPPED else Path(value).expanduser()
