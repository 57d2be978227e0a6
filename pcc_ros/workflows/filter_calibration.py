"""``pcc calibrate-filter``: fit the evidence rule's weights and threshold, reproducibly.

Data (every detection becomes one row of the evidence terms of :mod:`pcc_ros.pipeline.filter` and a
true / false label):

* **real frames** (``--real``): a labelled KITTI set with a detector's results, e.g. KITTI
  tracking 0000 frames 0-19 with PointRCNN — real scans, real detections, real false ones;
* **SynthCars** (``--synth``): its simulated detector's true detections, and false ones from
  a simulator *matched to the real false detections*: each is a copy of a real false box
  (size, range, height above the ground, detector score) placed at a random bearing in the
  camera's field of view where the scan gives it about as many returns as the real one had
  (the best of ``CANDIDATES`` seeded placements); synthetic true scores are mapped, rank for
  rank, onto the (smoothed) real true detections' scores — so the score term has one scale;
* **KITTI object frames** (``--object``, optional): real scans whose labelled cars become
  true detections (with detector-like box noise and real true scores) and simulated false ones.

Fit: an L2-regularised logistic regression (Newton / IRLS, deterministic) of
``false ~ density + free_space + ground_gap + score`` (5 parameters), the real frames
weighted as much as the simulated ones together. Threshold: the smallest probability that
loses at most ``--max-lost`` of the true detections of *each* source (real, SynthCars, object).
Synthetic true scores follow a smoothed map of the real ones (:func:`score_quantiles`).

Honesty: ``--folds K`` also runs leave-frames-out cross-validation over the real frames
(contiguous blocks of frames; the simulator's templates and the fit see only the training
frames) and reports the held-out operating figures. Same inputs and seed, same output.
"""

from __future__ import annotations

import json
import logging
import re
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, Self

import numpy as np
from scipy.special import ndtr

from pcc_ros.errors import ConfigError, DataError
from pcc_ros.geometry.boxes import iou_bev, points_in_boxes
from pcc_ros.pipeline.filter import (
    EVIDENCE_GROUND,
    TERMS,
    FilterConfig,
    filter_terms,
    local_ground,
    score_logit,
    term_matrix,
)
from pcc_ros.types import Boxes, class_mask
from pcc_ros.workflows.detection_eval import (
    auc,
    detection_truth,
    operating_curve,
    removed_at,
)

log = logging.getLogger(__name__)

#: Terms the calibration fits (the mismatch term joins once a car-constrained backend exists).
FIT_TERMS = ("density", "free_space", "ground_gap", "score")
CANDIDATES = 48  # seeded placements tried per simulated false detection
CAMERA_HALF_FOV = np.deg2rad(40.0)  # KITTI's colour camera sees about +-40 deg


class FeatureRows:
    """Rows of a dataclass whose first fields are ``x (N, len(TERMS))`` (the terms) and ``false``
    (1 = false detection), then label columns (object arrays, one value a row): joined and
    selected field by field, so each calibration keeps its own labels and one copy of this."""

    x: np.ndarray
    false: np.ndarray

    @classmethod
    def concatenate(cls, parts: list[Self]) -> Self:
        parts = [p for p in parts if len(p.false)]
        names = [f.name for f in fields(cls)]
        if not parts:
            labels = (np.zeros(0, object) for _ in names[2:])
            return cls(np.zeros((0, len(TERMS))), np.zeros(0, bool), *labels)
        return cls(*(np.concatenate([getattr(p, name) for p in parts]) for name in names))

    def subset(self, mask: np.ndarray) -> Self:
        return type(self)(*(getattr(self, f.name)[mask] for f in fields(self)))


@dataclass
class Table(FeatureRows):
    """Evidence rows: features ``x (N, len(TERMS))``, labels (1 = false detection), frame group,
    source ("real" / "synth" / "object") and the real false-box statistics when from ``real``."""

    x: np.ndarray
    false: np.ndarray
    group: np.ndarray
    source: np.ndarray


@dataclass
class FalseTemplates:
    """Statistics of real false detections the simulator copies: one row each."""

    size: np.ndarray  # (K, 3)
    range: np.ndarray  # (K,)
    points: np.ndarray  # (K,) returns in the box (evidence n_in)
    gap: np.ndarray  # (K,) signed height of the box bottom above the local ground
    score: np.ndarray  # (K,) raw detector score
    rate: float  # false detections per frame
    true_scores: np.ndarray  # raw scores of the real true detections


# ----------------------------------------------------------------------------- logistic regression


def fit_logistic(x: np.ndarray, y: np.ndarray, weight: np.ndarray | None = None, l2: float = 1e-2,
                 iterations: int = 50) -> tuple[float, np.ndarray]:
    """L2-regularised logistic regression by Newton's method: (bias, weights). Deterministic.

    Features are standardised inside (the penalty is on standardised weights; the bias is not
    penalised); the returned weights apply to the raw features.
    """
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    w = np.ones(len(y)) if weight is None else np.asarray(weight, dtype=np.float64)
    w = w / w.mean()
    mu, sd = x.mean(axis=0), x.std(axis=0)
    sd = np.where(sd > 1e-9, sd, 1.0)
    z = np.c_[np.ones(len(x)), (x - mu) / sd]
    beta = np.zeros(z.shape[1])
    penalty = np.full(z.shape[1], l2 * len(y))
    penalty[0] = 0.0
    for _ in range(iterations):
        p = 1.0 / (1.0 + np.exp(-np.clip(z @ beta, -30, 30)))
        grad = z.T @ (w * (p - y)) + penalty * beta
        hess = (z * (w * p * (1 - p))[:, None]).T @ z + np.diag(penalty + 1e-9)
        step = np.linalg.solve(hess, grad)
        beta -= step
        if np.abs(step).max() < 1e-10:
            break
    weights = beta[1:] / sd
    bias = beta[0] - float((beta[1:] * mu / sd).sum())
    return float(bias), weights


def predict(bias: float, weights: np.ndarray, x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-(bias + x @ weights)))


def threshold_for(p: np.ndarray, false: np.ndarray, max_lost: float) -> float:
    """Smallest probability threshold (reject ``p > t``) losing at most ``max_lost`` of the true rows."""
    true_p = np.sort(p[~false])[::-1]
    if not len(true_p):
        return 0.5
    allowed = int(np.floor(max_lost * len(true_p)))
    t = true_p[allowed] if allowed < len(true_p) else 0.0
    return float(min(max(t + 1e-6, 1e-6), 1 - 1e-6))


def threshold_each(p: np.ndarray, false: np.ndarray, group: np.ndarray, max_lost: float) -> float:
    """Smallest threshold losing at most ``max_lost`` of the true rows of *every* ``group`` (a
    sensor, the real frames): the worst group decides. A threshold on the pooled rows loses
    ``max_lost`` on average and more on the sensor with the most sparse, occluded true cars;
    an unknown sensor may be that one."""
    groups = np.unique(group[~false])
    if not len(groups):
        return threshold_for(p, false, max_lost)
    return max(threshold_for(p[group == g], false[group == g], max_lost) for g in groups)


# ----------------------------------------------------------------------------- data


def _columns(terms: dict[str, np.ndarray]) -> np.ndarray:
    return term_matrix(terms)


def real_table(frames, config: FilterConfig, gt_classes, true_iou: float) -> tuple[Table, FalseTemplates]:
    """Evidence rows of real detections, and the false ones as simulator templates."""
    xs, labels, groups, sizes, ranges, points, gaps, scores, true_scores = [], [], [], [], [], [], [], [], []
    for f in frames:
        truth = detection_truth(f, gt_classes, true_iou)
        known = truth >= 0
        boxes = f.dt.boxes[known]
        if not len(boxes):
            continue
        terms = filter_terms(f.points, boxes, config)
        xs.append(_columns(terms))
        false = truth[known] == 0
        labels.append(false)
        groups.append(np.full(len(boxes), f.name, dtype=object))
        sizes.append(boxes.size[false])
        ranges.append(np.linalg.norm(boxes.center[false, :2], axis=1))
        points.append(terms["n_in"][false])
        bottom = boxes.center[:, 2] - boxes.size[:, 2] / 2
        gaps.append(np.nan_to_num(bottom - terms["ground_z"], nan=0.0)[false])
        scores.append(boxes.score[false])
        true_scores.append(boxes.score[~false])
    if not xs:
        raise DataError("no real detections with a known truth to calibrate on")
    table = Table(np.concatenate(xs), np.concatenate(labels), np.concatenate(groups),
                  np.full(sum(len(x) for x in xs), "real", dtype=object))
    templates = FalseTemplates(
        np.concatenate(sizes), np.concatenate(ranges), np.concatenate(points), np.concatenate(gaps),
        np.concatenate(scores), float(table.false.sum()) / max(len(frames), 1), np.concatenate(true_scores),
    )
    if not len(templates.range) or not len(templates.true_scores):
        raise DataError("the real frames need both true and false detections to calibrate on")
    return table, templates


def simulate_false(points: np.ndarray, gt: Boxes, templates: FalseTemplates, rng: np.random.Generator,
                   count: int) -> Boxes:
    """``count`` false detections that look like the real ones (see the module docstring)."""
    if count == 0:
        return Boxes.empty()
    k = len(templates.range)
    pick = rng.integers(0, k, count)
    m = CANDIDATES
    r = np.repeat(templates.range[pick], m) * np.exp(rng.normal(0.0, 0.1, count * m))
    bearing = rng.uniform(-CAMERA_HALF_FOV, CAMERA_HALF_FOV, count * m)
    size = np.repeat(templates.size[pick], m, axis=0)
    yaw = rng.uniform(-np.pi, np.pi, count * m)
    centre = np.c_[r * np.cos(bearing), r * np.sin(bearing), np.zeros(count * m)]
    flat = Boxes(centre, size, yaw)
    ground = local_ground(points, flat)
    ground = np.where(np.isfinite(ground), ground, np.nanmedian(ground) if np.isfinite(ground).any() else -1.73)
    centre[:, 2] = ground + np.repeat(templates.gap[pick], m) + size[:, 2] / 2
    cands = Boxes(centre, size, yaw, ["Car"] * (count * m), np.repeat(templates.score[pick], m))
    n = np.array([len(i) for i in points_in_boxes(points, cands, 0.0, EVIDENCE_GROUND)], dtype=np.float64)
    cost = np.abs(np.log1p(n) - np.log1p(np.repeat(templates.points[pick], m)))
    if len(gt):
        cost[iou_bev(cands, gt).max(axis=1) > 0.05] = np.inf
    best = np.argmin(cost.reshape(count, m), axis=1) + np.arange(count) * m
    ok = np.isfinite(cost[best])
    return cands[best[ok]]


def _map_scores(raw: np.ndarray, reference: np.ndarray, mapping: str) -> np.ndarray:
    """Rank-for-rank map of ``raw`` onto the distribution of ``reference`` (quantile mapping,
    smoothed: :func:`score_quantiles`)."""
    if not len(raw):
        return raw
    ranks = (np.argsort(np.argsort(raw, kind="stable"), kind="stable") + 0.5) / len(raw)
    return score_quantiles(ranks, reference, mapping)


def score_quantiles(q: np.ndarray, reference: np.ndarray, mapping: str) -> np.ndarray:
    """Quantiles ``q`` of the real true scores ``reference``, smoothed. The reference is a
    handful of scores (two tracks give ~30), and the plain quantiles of so few stop at their
    smallest: no synthetic true car would carry a lower score than the lowest real one seen,
    yet the threshold spares the lowest 1 % of thousands of synthetic cars, where a real
    detector's true scores run lower (a car entering view, far or occluded). These are the
    quantiles of a Gaussian kernel density of the reference (Silverman's bandwidth; no free
    parameter), in the score term's logit space, written back in ``mapping``'s raw scale."""
    q = np.asarray(q, dtype=np.float64)
    logits = score_logit(reference, mapping)
    h = silverman_bandwidth(logits)
    if h <= 0.0:
        return np.quantile(reference, q)
    grid = np.linspace(logits.min() - 6 * h, logits.max() + 6 * h, 4096)
    cdf = ndtr((grid[:, None] - logits[None, :]) / h).mean(axis=1)
    mapped = np.interp(q, cdf, grid)
    return mapped if mapping == "sigmoid" else 1.0 / (1.0 + np.exp(-mapped))


def silverman_bandwidth(values: np.ndarray) -> float:
    """Silverman's rule-of-thumb kernel bandwidth, ``0.9 min(sd, IQR / 1.34) n^(-1/5)``
    (the sd alone where the IQR is 0); 0 for fewer than two distinct values."""
    values = np.asarray(values, dtype=np.float64)
    if len(values) < 2:
        return 0.0
    sd = float(values.std(ddof=1))
    iqr = float(np.subtract(*np.quantile(values, [0.75, 0.25]))) / 1.34
    spread = min(sd, iqr) if iqr > 0 else sd
    return 0.9 * spread * len(values) ** -0.2


def simulated_table(frames, templates: FalseTemplates, config: FilterConfig, rng: np.random.Generator,
                    source: str, true_iou: float, jitter: bool) -> Table:
    """SynthCars (``jitter=False``: its detector's true detections) or real object frames
    (``jitter=True``: labelled cars with detector-like noise) plus simulated false detections."""
    tables = []
    for f in frames:
        cars = f.gt.boxes[class_mask(f.gt.boxes.label, ("Car", "Van"))]
        if jitter:
            n = len(cars)
            true = Boxes(
                cars.center + rng.normal(0, 0.1, (n, 3)) * [1, 1, 0.5],
                cars.size * np.exp(rng.normal(0, 0.03, (n, 3))),
                cars.yaw + rng.normal(0, 0.05, n),
                ["Car"] * n,
                score_quantiles(rng.random(n), templates.true_scores, config.score_mapping),
            )
        else:
            truth = detection_truth(f, ("Car", "Van"), true_iou)
            true = f.dt.boxes[truth == 1]
            true.score = _map_scores(true.score, templates.true_scores, config.score_mapping)
        fake = simulate_false(f.points, f.gt.boxes, templates, rng, int(rng.poisson(templates.rate)))
        boxes = Boxes.concatenate([true, fake])
        if not len(boxes):
            continue
        terms = filter_terms(f.points, boxes, config)
        tables.append(Table(
            _columns(terms), np.r_[np.zeros(len(true), bool), np.ones(len(fake), bool)],
            np.full(len(boxes), f"{source}:{f.name}", dtype=object), np.full(len(boxes), source, dtype=object),
        ))
    return Table.concatenate(tables)


# ----------------------------------------------------------------------------- fit


def fit(
    table: Table, max_lost: float, l2: float, terms: tuple[str, ...] = FIT_TERMS
) -> tuple[float, np.ndarray, float]:
    """(bias, weights over TERMS, threshold); real rows weigh as much as all simulated ones. The
    threshold loses at most ``max_lost`` of the true rows of *each* source (real, synth,
    object), as the sensor calibration does per sensor: on the pooled rows the thousands of
    simulated cars would let the budget fall on the few real ones."""
    cols = [TERMS.index(t) for t in terms]
    real = table.source == "real"
    weight = np.ones(len(table.false))
    if real.any() and (~real).any():
        weight[real] = (~real).sum() / real.sum()
    bias, w = fit_logistic(table.x[:, cols], table.false, weight, l2)
    weights = np.zeros(len(TERMS))
    weights[cols] = w
    p = predict(bias, weights, table.x)
    return bias, weights, threshold_each(p, table.false, table.source, max_lost)


def calibrate(real_frames, synth_frames, object_frames, config: FilterConfig, seed: int, gt_classes,
              true_iou: float = 0.3, max_lost: float = 0.01, l2: float = 1e-2,
              terms: tuple[str, ...] = FIT_TERMS) -> dict[str, Any]:
    """Tables, fit and the in-sample figures (see :func:`cross_validate` for held-out ones)."""
    rng = np.random.default_rng(seed)
    real, templates = real_table(real_frames, config, gt_classes, true_iou)
    synth = simulated_table(synth_frames, templates, config, rng, "synth", true_iou, jitter=False)
    obj = simulated_table(object_frames, templates, config, rng, "object", true_iou, jitter=True)
    table = Table.concatenate([real, synth, obj])
    bias, weights, threshold = fit(table, max_lost, l2, terms)
    summary = {}
    for name in ("real", "synth", "object"):
        part = table.subset(table.source == name)
        if not len(part.false):
            continue
        p = predict(bias, weights, part.x)
        summary[name] = _figures(p, part.false, threshold, max_lost)
    return {"bias": bias, "weights": weights, "threshold": threshold, "table": table, "in_sample": summary,
            "templates": templates}


def _figures(p: np.ndarray, false: np.ndarray, threshold: float, max_lost: float) -> dict[str, Any]:
    curve = operating_curve(p, ~false)
    best, _ = removed_at(curve, 0.02)
    reject = p > threshold
    return {
        "detections": len(p), "false": int(false.sum()), "true": int((~false).sum()),
        "false_removed_at_threshold": float(reject[false].mean()) if false.any() else float("nan"),
        "true_lost_at_threshold": float(reject[~false].mean()) if (~false).any() else float("nan"),
        "false_removed_at_0.02_lost_best": best,
        "auc_false_above_true": auc(p, ~false),
    }


def cross_validate(real_frames, synth_frames, object_frames, config: FilterConfig, seed: int, gt_classes,
                   folds: int, true_iou: float = 0.3, max_lost: float = 0.01, l2: float = 1e-2,
                   terms: tuple[str, ...] = FIT_TERMS) -> dict[str, Any]:
    """Leave-frames-out over the real frames: contiguous blocks (neighbouring tracking frames
    see the same objects, so random splits would leak). Each fold: templates, simulation and
    fit from the training frames only; the held-out real detections are scored with the
    fold's weights *and threshold*. Returns pooled held-out figures and per-fold weights."""
    if folds < 2 or folds > len(real_frames):
        raise ConfigError(f"--folds must be between 2 and the number of real frames ({len(real_frames)})")
    blocks = np.array_split(np.arange(len(real_frames)), folds)
    p_all, false_all, reject_all, per_fold = [], [], [], []
    for k, held in enumerate(blocks):
        train = [f for i, f in enumerate(real_frames) if i not in set(held.tolist())]
        test = [real_frames[i] for i in held]
        fitted = calibrate(train, synth_frames, object_frames, config, seed + 1000 * (k + 1), gt_classes,
                           true_iou, max_lost, l2, terms)
        test_table, _ = _real_rows(test, config, gt_classes, true_iou)
        if test_table is None:
            continue
        p = predict(fitted["bias"], fitted["weights"], test_table.x)
        p_all.append(p)
        false_all.append(test_table.false)
        reject_all.append(p > fitted["threshold"])
        per_fold.append({"frames": [f.name for f in test], "bias": fitted["bias"],
                         "weights": dict(zip(TERMS, fitted["weights"].tolist())), "threshold": fitted["threshold"]})
    p, false, reject = np.concatenate(p_all), np.concatenate(false_all), np.concatenate(reject_all)
    figures = _figures(p, false, 0.5, max_lost)
    figures["false_removed_at_fold_threshold"] = float(reject[false].mean())
    figures["true_lost_at_fold_threshold"] = float(reject[~false].mean())
    figures.pop("false_removed_at_threshold")
    figures.pop("true_lost_at_threshold")
    return {"folds": per_fold, "held_out": figures}


def _real_rows(frames, config, gt_classes, true_iou):
    try:
        table, _ = real_table(frames, config, gt_classes, true_iou)
    except DataError:
        xs, labels = [], []
        for f in frames:
            truth = detection_truth(f, gt_classes, true_iou)
            known = truth >= 0
            if known.any():
                xs.append(_columns(filter_terms(f.points, f.dt.boxes[known], config)))
                labels.append(truth[known] == 0)
        if not xs:
            return None, None
        table = Table(np.concatenate(xs), np.concatenate(labels), np.zeros(0, object), np.zeros(0, object))
    return table, None


# ----------------------------------------------------------------------------- output


def preset_yaml(base: Path, bias: float, weights: np.ndarray, threshold: float, values: dict[str, Any],
                header: str) -> str:
    """The node YAML ``base`` with the calibrated filter parameters put in: each key's line is
    rewritten in place (indentation and trailing comment kept), missing keys are appended to
    the ``ros__parameters`` block; everything else of the file stays as it was. A base's
    ``sensor_thresholds`` and ``trees`` belong to the base's weights, so the file gets ``""`` for
    both (its own threshold for every sensor, the weighted sum alone) unless ``values`` brings them
    for the new ones."""
    try:
        lines = base.read_text().splitlines()
    except OSError as exc:
        raise DataError(f"{base}: cannot read the base node YAML ({exc.strerror})") from exc
    params = {"sensor_thresholds": "", "trees": "", **values, "rule": "evidence", "w_bias": round(float(bias), 4)}
    params.update({f"w_{t}": round(float(w), 4) for t, w in zip(TERMS, weights)})
    params["reject_threshold"] = round(float(threshold), 4)
    block = next((i for i, line in enumerate(lines) if line.strip() == "ros__parameters:"), None)
    if block is None:
        raise DataError(f"{base}: no 'ros__parameters:' block")
    indent = next((re.match(r"\s*", line).group(0) for line in lines[block + 1:] if line.strip()), "    ")
    for key, value in params.items():
        pattern = re.compile(rf"^({re.escape(indent)}){re.escape(key)}:\s*([^#]*?)(\s*#.*)?$")
        plain = isinstance(value, str) and re.fullmatch(r"[A-Za-z_][\w.-]*", value) is not None
        text = value if plain else json.dumps(value) if isinstance(value, str) else repr(value)
        for i, line in enumerate(lines):
            m = pattern.match(line)
            if m:
                comment = VALUE_COMMENTS.get((key, value), m.group(3) or "")
                lines[i] = f"{m.group(1)}{key}: {text}{comment}"
                break
        else:
            lines.append(f"{indent}{key}: {text}")
    body = [line for line in lines if not line.startswith("# calibrated:")]
    return header + "\n".join(body) + "\n"


#: A base line's trailing comment describes the base's value; where a preset writes another value
#: whose meaning differs, this comment replaces it (keyed by parameter and written value).
VALUE_COMMENTS: dict[tuple[str, Any], str] = {
    ("sensor", "hdl64"): "                 # KITTI's HDL-64E datasheet table; auto: estimated from the scans",
}

#: The lines a preset's file opens with, after the command that wrote it: what it is for.
PRESET_NOTES: dict[str, str] = {
    "kitti": "# The KITTI + PointRCNN preset (score term in PointRCNN's logits: run with score_mapping:=sigmoid); the\n"
             "# shipped default (detection_filter.yaml) is the sensor- and detector-agnostic rule (docs/filter.md).\n",
}

#: What a preset writes besides the fitted weights: sensor model and score mapping. Both write
#: ``score_mapping: identity`` (the project's convention: shipped configs assume probabilities;
#: a logit detector such as PointRCNN sets ``sigmoid``): the score term is a logit either way,
#: so weights fitted on logits hold for a detector that outputs sigmoid(logit).
PRESETS: dict[str, dict[str, Any]] = {
    "kitti": {"score_mapping": "identity"},
    "nuscenes": {"sensor": "auto", "score_mapping": "identity", "match_threshold": 0.4},
}
