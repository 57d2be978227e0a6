"""One evidence rule for every sensor: ``pcc calibrate-filter --sim-sensors ...`` / ``--sensor X``.

The rule's terms are normalised by the beam model (``density`` compares the returns with what
the sensor's own beams would give a car there; ``free_space`` is a ratio of rays; the ground gap
is metres), so one weight set can serve any sensor. This module fits that one weight set on:

* **simulated sensors**: SynthCars generated with each beam layout of ``sensors`` (cached under
  ``root/<layout>_s<seed>``, resumable, deterministic), its detector's four labelled kinds of
  false positives (confusion, ghost, far, misplaced; ``docs/synthcars.md``) and true detections;
* **real labelled frames** (optional): a KITTI root with a real detector's results (KITTI
  tracking 0000 with PointRCNN), true / false by BEV IoU as ``pcc eval detections`` decides.

Every row is measured by the node's own pipeline (:class:`pcc_ros.pipeline.core.Pipeline`, the
completion skipped, ``max_instances`` lifted so that every box is judged) with the simulated
sensor's beam model; the shape ``mismatch`` comes from a car-constrained completion
(``filter_backend``, TraPCC by default). Fit: the L2 logistic regression of
:mod:`pcc_ros.workflows.filter_calibration`, each sensor's rows and the real rows weighing the same.
Threshold: the smallest that loses at most ``max_lost`` of each sensor's true detections (and
of the real frames'): safe on the worst sensor, not on the average. ``max_lost="cv"`` makes that
budget a choice of the calibration (:func:`choose_budget`): the largest of :data:`BUDGET_GRID`
whose leave-one-sensor-out folds each lose at most ``target_lost`` of the held-out sensor's true
cars — what an unknown sensor is promised — and, one level further out, each sensor held out of
that choice too (``budget_selection.nested``): the loss of a sensor the budget never saw.

Honesty: leave-one-group-out cross-validation **by sensor** (fit on the other sensors and the
real frames, judge the held-out sensor at the fold's own threshold, per false-positive kind) and
**by sequence** (every SynthCars sequence and every block of real frames held out in turn);
an **ablation** refits without each term and reports what the held-out figures lose, and the
mismatch term's own AUC on confusions (non-vehicles boxed as cars) against true cars.
The detector score is not among the default terms: the score scale of an unknown detector is
unknown, and a score term could reject real cars on its own (``--terms`` adds it for a known one).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from pcc_ros.errors import ConfigError
from pcc_ros.pipeline.filter import TERMS, FilterConfig, rule_logit, term_matrix
from pcc_ros.pipeline.trees import TermTrees
from pcc_ros.workflows.detection_eval import auc, detection_truth, load_kitti, operating_curve, removed_at
from pcc_ros.workflows.filter_calibration import FeatureRows, fit_logistic, predict, threshold_each

log = logging.getLogger(__name__)

#: Beam layouts simulated by default (``pcc_ros.geometry.beams.SENSOR_PRESETS`` names).
DEFAULT_SENSORS = ("hdl64", "vlp16", "vlp32c", "os1_64")
#: Terms fitted by default: scan evidence only. No detector score (an unknown detector's scale is
#: unknown); the shape ``mismatch`` is opt-in (``--terms``): it costs a car-constrained completion of
#: every box and, measured across the simulated sensors, buys ranking but no removal at 2 % lost.
SENSOR_TERMS = ("density", "free_space", "ground_gap")
#: Per-sensor loss budgets ``max_lost="cv"`` chooses from (a share of each sensor's true cars the
#: threshold may reject): 0.5-2 % in quarter-point steps. The held-out loss grows with the budget
#: (the weights do not depend on it, only the threshold), so the largest budget within the target
#: is the one that removes the most.
BUDGET_GRID = (0.005, 0.0075, 0.01, 0.0125, 0.015, 0.0175, 0.02)


def parse_terms(text: str | None, default: tuple[str, ...]) -> tuple[str, ...]:
    """``--terms``: comma-separated names of :data:`TERMS` (``default`` when empty)."""
    terms = tuple(t.strip() for t in (text or ",".join(default)).split(",") if t.strip())
    unknown = set(terms) - set(TERMS)
    if unknown or not terms:
        raise ConfigError(f"--terms: unknown {sorted(unknown)} (have {', '.join(TERMS)})")
    return terms


@dataclass
class Rows(FeatureRows):
    """One row per detection: features over :data:`TERMS`, label (1 = false), kind, sensor,
    group (the cross-validation unit: a SynthCars sequence or a block of real frames)."""

    x: np.ndarray
    false: np.ndarray
    kind: np.ndarray
    sensor: np.ndarray
    group: np.ndarray


def synth_dataset(root: Path, layout: str, seed: int, sequences: int, frames: int, sensor=None) -> Path:
    """SynthCars of one beam layout under ``root/<layout>_s<seed>`` (generated once, then reused);
    ``sensor``: a :class:`~pcc_ros.data.synthetic.lidar.Sensor` of its own (a sensor read from a
    user's scans) instead of the preset ``layout``."""
    from pcc_ros.data.synthetic import generate
    from pcc_ros.data.synthetic.lidar import Sensor

    out = Path(root) / f"{layout}_s{seed}"
    generate(out, sequences, frames, seed, sensor=sensor or Sensor(layout=layout), test_fraction=0.0)
    return out


def measuring_pipeline(filter_backend: str, shape: bool = True, device: str = "cpu"):
    """The node's pipeline set to measure every term of every box (no completion of its own);
    ``shape``: also the mismatch against ``filter_backend``'s completion (else NaN, read as 0)."""
    from pcc_ros.workflows.detection_eval import build_pipeline

    pipeline = build_pipeline(None, {"backend": "input", "device": device, "w_mismatch": 1.0 if shape else 0.0,
                                     "filter_backend": filter_backend})
    pipeline.config = replace(pipeline.config, max_instances=100_000)
    return pipeline


def _measure(pipeline, sensor: str, frames, truth_of, kind_of, group_of, label: str) -> Rows:
    """Rows of ``frames``, the beam model ``sensor`` (``auto``: estimated from the scans as the node
    does, afresh for every sequence: a new sequence may be another sensor)."""
    from pcc_ros.pipeline.beam_model import BeamModel

    pipeline.config = replace(pipeline.config, filter=replace(pipeline.config.filter, sensor=sensor))
    parts, last = [], None
    for f in tqdm(frames, desc=f"rows {label}", unit="frame"):
        if group_of(f) != last:
            pipeline.beam_model, last = BeamModel(sensor), group_of(f)
        keep = truth_of(f) >= 0
        boxes = f.dt.boxes[keep]
        if not len(boxes):
            continue
        result = pipeline.process(f.points, boxes)
        terms = {t: result.filter_terms.get(t, np.full(len(boxes), np.nan)) for t in TERMS}
        n = len(boxes)
        x = term_matrix(terms)
        x[:, TERMS.index("mismatch")] = result.mismatch  # NaN where no shape was completed: filled at the fit
        parts.append(Rows(x, truth_of(f)[keep] == 0, kind_of(f)[keep],
                          np.full(n, label, dtype=object), np.full(n, group_of(f), dtype=object)))
    return Rows.concatenate(parts)


def judged_synth_frames(pipeline, root: Path, label: str = ""):
    """Every frame of a SynthCars root that holds detections, with the pipeline's result on them:
    ``(frame, boxes, result)``, the beam model estimated afresh for every sequence (as a node
    started on it would). For the diagnosis scripts, which read more of a result than a row."""
    from pcc_ros.pipeline.beam_model import BeamModel

    det_root = root / "detections" / "synthetic"
    for seq in sorted(p.name for p in (root / "training" / "velodyne").iterdir() if p.is_dir()):
        pipeline.beam_model = BeamModel(pipeline.config.filter.sensor)
        for f in tqdm(load_kitti(root, det_root, seq), desc=f"{label or root.name} {seq}", leave=False):
            if len(f.dt.boxes):
                yield f, f.dt.boxes, pipeline.process(f.points, f.dt.boxes)


def synth_rows(pipeline, root: Path, layout: str, sensor: str = "auto") -> Rows:
    """Rows of every frame of a SynthCars root simulated with ``layout`` (truth and kind from its
    ``.kind`` files), measured with the beam model ``sensor``."""
    split = root / "training" / "velodyne"
    frames = []
    for seq in sorted(p.name for p in split.iterdir() if p.is_dir()):
        frames += load_kitti(root, root / "detections" / "synthetic", seq)

    def kinds(f):
        return f.kinds if f.kinds is not None else np.full(len(f.dt.boxes), "true", dtype=object)

    return _measure(pipeline, sensor, frames, lambda f: (kinds(f) == "true").astype(np.int64), kinds,
                    lambda f: f"{layout}:{f.name.split('/')[0]}", layout)


def real_rows(pipeline, frames, sensor: str, gt_classes, block: int = 4) -> Rows:
    """Rows of real labelled frames (true / false by BEV IoU 0.3; DontCare left out); groups are
    blocks of ``block`` neighbouring frames (they see the same objects)."""
    index = {f.name: i for i, f in enumerate(frames)}
    return _measure(pipeline, sensor, frames, lambda f: detection_truth(f, gt_classes, 0.3),
                    lambda f: np.where(detection_truth(f, gt_classes, 0.3) == 1, "true", "real false"),
                    lambda f: f"real:{index[f.name] // block}", "real")


# ----------------------------------------------------------------------------- fit and judge


_MISMATCH = TERMS.index("mismatch")


def filled(x: np.ndarray, mismatch_mean: float) -> np.ndarray:
    """``x`` with a missing mismatch (NaN: no shape completed) read as ``mismatch_mean``, as the
    rule reads it (:func:`pcc_ros.pipeline.filter.term_matrix`)."""
    out = x.copy()
    out[:, _MISMATCH] = np.where(np.isfinite(out[:, _MISMATCH]), out[:, _MISMATCH], mismatch_mean)
    return out


def rows_probability(rows: Rows, config: FilterConfig, trees: TermTrees | None) -> np.ndarray:
    """p_false of every row under the weighted sum of ``config`` plus
    ``trees`` (a missing mismatch read as its mean); the trees are given, not read from ``config``'s
    file, so fold fits need none."""
    z = rule_logit(filled(rows.x, config.mismatch_mean), config.w_bias, config.weights, trees)
    return 1.0 / (1.0 + np.exp(-z))


def sensor_balance(rows: Rows) -> np.ndarray:
    """Row weights under which every sensor's rows (and the real frames') weigh the same in total."""
    weight = np.ones(len(rows.false))
    sensors = np.unique(rows.sensor)
    for s in sensors:
        sel = rows.sensor == s
        weight[sel] = len(rows.false) / (sel.sum() * len(sensors))
    return weight


def fit_weights(rows: Rows, terms: tuple[str, ...], l2: float) -> tuple[float, np.ndarray, float, np.ndarray]:
    """(bias, weights over TERMS, mismatch_mean, p_false of every row); every sensor's rows (and
    the real ones) weigh the same; ``mismatch_mean``: the mean measured mismatch of these rows.
    The loss budget plays no part: it only sets the threshold on ``p_false`` (:func:`fit_rows`)."""
    measured = rows.x[:, _MISMATCH][np.isfinite(rows.x[:, _MISMATCH])]
    mean = float(measured.mean()) if len(measured) and "mismatch" in terms else 0.0
    x = filled(rows.x, mean)
    cols = [TERMS.index(t) for t in terms]
    bias, w = fit_logistic(x[:, cols], rows.false, sensor_balance(rows), l2)
    weights = np.zeros(len(TERMS))
    weights[cols] = w
    return bias, weights, mean, predict(bias, weights, x)


def fit_rows(rows: Rows, terms: tuple[str, ...], max_lost: float, l2: float
             ) -> tuple[float, np.ndarray, float, float]:
    """(bias, weights over TERMS, threshold, mismatch_mean): :func:`fit_weights`, and the threshold
    that loses at most ``max_lost`` of each sensor's true rows
    (:func:`~pcc_ros.workflows.filter_calibration.threshold_each`)."""
    bias, weights, mean, p = fit_weights(rows, terms, l2)
    return bias, weights, threshold_each(p, rows.false, rows.sensor, max_lost), mean


def figures(p: np.ndarray, rows: Rows, reject: np.ndarray) -> dict[str, Any]:
    """Removed / lost at the given decisions, per kind, the best removal at <= 2 % lost and AUC."""
    true = ~rows.false
    best, _ = removed_at(operating_curve(p, true), 0.02)
    out = {"true": int(true.sum()), "false": int(rows.false.sum()),
           "true_lost": float(reject[true].mean()) if true.any() else float("nan"),
           "false_removed": float(reject[rows.false].mean()) if rows.false.any() else float("nan"),
           "false_removed_at_0.02_lost_best": best, "auc_false_above_true": auc(p, true), "per_kind": {}}
    for k in sorted(set(rows.kind[rows.false])):
        sel = rows.kind == k
        out["per_kind"][k] = {"count": int(sel.sum()), "removed": float(reject[sel].mean()),
                              "auc_vs_true": auc(np.r_[p[sel], p[true]], np.r_[np.zeros(sel.sum(), bool),
                                                                               np.ones(true.sum(), bool)])}
    return out


def leave_one_out(rows: Rows, by: np.ndarray, terms, max_lost: float, l2: float,
                  only: np.ndarray | None = None) -> dict[str, Any]:
    """Leave-one-group-out: each value of ``by`` held out in turn (only those where ``only``);
    the held-out rows are judged with the fold's weights and threshold. Pooled and per group."""
    p = np.full(len(rows.false), np.nan)
    reject = np.zeros(len(rows.false), bool)
    folds = {}
    for g in np.unique(by[only] if only is not None else by):
        test = by == g
        train = ~test
        if rows.false[train].all() or not rows.false[train].any():
            continue
        bias, weights, threshold, mean = fit_rows(rows.subset(train), terms, max_lost, l2)
        p[test] = predict(bias, weights, filled(rows.x[test], mean))
        reject[test] = p[test] > threshold
        folds[str(g)] = {"threshold": threshold, "weights": dict(zip(TERMS, np.round(weights, 4).tolist())),
                         **figures(p[test], rows.subset(test), reject[test])}
    held = np.isfinite(p)
    return {"pooled": figures(p[held], rows.subset(held), reject[held]), "folds": folds}


def _held_out_lost(rows: Rows, terms, grid: tuple[float, ...], l2: float) -> dict[float, dict[str, float]]:
    """Per budget of ``grid``, per simulated sensor held out (as :func:`leave_one_out` by sensor):
    the share of its true cars lost at the fold's threshold for that budget. One fit per fold, its
    threshold set for every budget: the weights do not depend on the budget."""
    lost: dict[float, dict[str, float]] = {b: {} for b in grid}
    for s in np.unique(rows.sensor[rows.sensor != "real"]):
        test = rows.sensor == s
        train = rows.subset(~test)
        if train.false.all() or not train.false.any():
            continue
        bias, weights, mean, p_train = fit_weights(train, terms, l2)
        p_true = predict(bias, weights, filled(rows.x[test & ~rows.false], mean))
        for b in grid:
            threshold = threshold_each(p_train, train.false, train.sensor, b)
            lost[b][str(s)] = float((p_true > threshold).mean()) if len(p_true) else float("nan")
    return lost


def choose_budget(rows: Rows, terms: tuple[str, ...], l2: float = 1e-2, target_lost: float = 0.02,
                  grid: tuple[float, ...] = BUDGET_GRID, nested: bool = True) -> dict[str, Any]:
    """The per-sensor loss budget by leave-one-sensor-out cross-validation: the largest of ``grid``
    at which every simulated sensor, held out in turn (fitted and thresholded on the others and the
    real rows), loses at most ``target_lost`` of its true cars. A budget chosen so sits at the
    folds' edge; ``nested`` also holds each sensor out of the choice itself (the budget chosen on
    the others alone, then that sensor judged at it): the loss to expect on a sensor never seen.

    Raises :class:`ConfigError` naming each budget's worst held-out loss when none meets the
    target (the rule cannot promise it on an unknown sensor), or with fewer than 2 sensors.
    """
    sim = rows.sensor != "real"
    sensors = np.unique(rows.sensor[sim])
    if len(sensors) < 2:
        raise ConfigError("--max-lost cv holds out each simulated sensor in turn: give two or more "
                          f"--sim-sensors (have {', '.join(map(str, sensors)) or 'none'})")
    per_sensor = _held_out_lost(rows, terms, grid, l2)
    worst = {b: max(per_sensor[b].values()) for b in grid}
    ok = [b for b in grid if worst[b] <= target_lost + 1e-12]
    report = {"target_lost": target_lost, "grid": list(grid),
              "worst_held_out_lost": [worst[b] for b in grid],
              "held_out_lost": {f"{b:g}": per_sensor[b] for b in grid}}
    if not ok:
        tried = ", ".join(f"{b:.2%}: {worst[b]:.2%}" for b in grid)
        raise ConfigError(f"--max-lost cv: no budget keeps every held-out sensor's loss at or under "
                          f"{target_lost:.2%} (budget: worst held-out loss {tried}); raise --target-lost or give "
                          "--max-lost a number")
    report["chosen"] = max(ok)
    if nested and len(sensors) > 2:  # the inner choice needs two sensors left to hold out
        report["nested"] = {}
        for s in sensors:
            out = rows.sensor == s
            inner = rows.subset(~out)
            inner_lost = _held_out_lost(inner, terms, grid, l2)
            ok_inner = [b for b in grid if max(inner_lost[b].values()) <= target_lost + 1e-12]
            if not ok_inner:
                report["nested"][str(s)] = {"budget": None}
                continue
            bias, weights, threshold, mean = fit_rows(inner, terms, max(ok_inner), l2)
            p = predict(bias, weights, filled(rows.x[out], mean))
            fig = figures(p, rows.subset(out), p > threshold)
            report["nested"][str(s)] = {"budget": max(ok_inner), "threshold": threshold,
                                        "true_lost": fig["true_lost"], "false_removed": fig["false_removed"]}
    return report


def calibrate_sensors(rows: Rows, terms: tuple[str, ...], max_lost: float | str = 0.01, l2: float = 1e-2,
                      target_lost: float = 0.02) -> dict[str, Any]:
    """The fit on every row, the cross-validation by sensor and by sequence, the ablation.
    ``max_lost="cv"``: the budget chosen by :func:`choose_budget` for ``target_lost`` (recorded
    under ``budget_selection``), then everything else at it."""
    selection = None
    if max_lost == "cv":
        selection = choose_budget(rows, terms, l2, target_lost)
        max_lost = selection["chosen"]
    elif not isinstance(max_lost, float | int):
        raise ConfigError(f"max_lost must be a share of true detections or 'cv', got {max_lost!r}")
    bias, weights, threshold, mean = fit_rows(rows, terms, max_lost, l2)
    x = filled(rows.x, mean)
    p = predict(bias, weights, x)
    sim = rows.sensor != "real"
    out: dict[str, Any] = {
        "terms": list(terms), "bias": bias, "weights": dict(zip(TERMS, weights.tolist())), "threshold": threshold,
        "mismatch_mean": mean, "max_lost": max_lost,
        **({"budget_selection": selection} if selection is not None else {}),
        "rows": {str(s): {"true": int((~rows.false[rows.sensor == s]).sum()),
                          "false": int(rows.false[rows.sensor == s].sum())} for s in np.unique(rows.sensor)},
        "in_sample": figures(p, rows, p > threshold),
    }
    if len(np.unique(rows.sensor[sim])) > 1:
        out["cv_by_sensor"] = leave_one_out(rows, rows.sensor, terms, max_lost, l2, only=sim)
    out["cv_by_sequence"] = leave_one_out(rows, rows.group, terms, max_lost, l2)
    real = rows.sensor == "real"
    if real.any():
        held = leave_one_out(rows, rows.group, terms, max_lost, l2, only=real)
        out["cv_real_frames"] = held["pooled"]
    ablation = {}
    for t in terms:
        rest = tuple(u for u in terms if u != t)
        if not rest:
            continue
        cv = leave_one_out(rows, rows.group, rest, max_lost, l2)["pooled"]
        full = out["cv_by_sequence"]["pooled"]
        ablation[t] = {
            "auc_without": cv["auc_false_above_true"], "auc_change": full["auc_false_above_true"]
            - cv["auc_false_above_true"],
            "removed_at_0.02_without": cv["false_removed_at_0.02_lost_best"],
            "removed_at_0.02_change": full["false_removed_at_0.02_lost_best"] - cv["false_removed_at_0.02_lost_best"],
            "confusion_auc_without": cv["per_kind"].get("confusion", {}).get("auc_vs_true", float("nan")),
        }
    out["ablation"] = ablation
    out["term_auc"] = term_auc(rows)
    if "mismatch" in terms:
        out["mismatch"] = mismatch_report(rows, out)
    return out


def term_auc(rows: Rows) -> dict[str, dict[str, float]]:
    """Each measured term alone: per false kind, the AUC of that kind's boxes scoring above the
    true ones (of the simulation for the simulated kinds, of the real frames for ``real false``;
    below 0.5: the term is lower on false boxes). What a term could bring, before any fit."""
    out: dict[str, dict[str, float]] = {}
    real = rows.sensor == "real"
    for t in TERMS:
        x = rows.x[:, TERMS.index(t)]
        if not np.isfinite(x).any() or np.nanstd(x) == 0:
            continue  # not measured (the shape without a completion; the score of one fixed value)
        out[t] = {}
        for kind in sorted(set(rows.kind[rows.false])):
            sel = (rows.kind == kind) | (~rows.false & (real == (kind == "real false")))
            sel &= np.isfinite(x)
            out[t][str(kind)] = auc(x[sel], ~rows.false[sel])
    return out


def mismatch_report(rows: Rows, result: dict[str, Any]) -> dict[str, Any]:
    """What the shape term brings: its weight, its own AUC on confusions vs true cars, and the
    held-out AUC on confusions with and without it."""
    m = rows.x[:, _MISMATCH]
    true, conf = ~rows.false, rows.kind == "confusion"
    sel = (true | conf) & np.isfinite(m)
    full = result["cv_by_sequence"]["pooled"]["per_kind"].get("confusion", {}).get("auc_vs_true", float("nan"))
    without = result["ablation"].get("mismatch", {}).get("confusion_auc_without", float("nan"))
    return {"weight": result["weights"]["mismatch"],
            "auc_alone_confusion_vs_true": auc(m[sel], true[sel]) if conf.any() else float("nan"),
            "auc_alone_all_false_vs_true": auc(m[np.isfinite(m)], true[np.isfinite(m)]),
            "measured_share": float(np.isfinite(m).mean()),
            "confusion_auc_held_out_with": full, "confusion_auc_held_out_without": without,
            "confusion_auc_contribution": full - without}
