"""Per-sensor reject thresholds for one weight set: ``pcc calibrate-filter --sensor-thresholds ...``.

One weight set serves every sensor (:mod:`pcc_ros.workflows.filter_sensors`), but one threshold
does not: the evidence a true car leaves differs with the beam layout and with how many
evidence-poor far cars the detector reports on it, so a threshold safe on the dense sensors
spares the sparse sensors' false boxes, and one fitted on four layouts loses more than the budget
on some others (docs/filter.md, "Per-sensor thresholds"). This module gives each beam layout its
own threshold for the *given* weights (fitted in the same command or read from a node YAML):

* the layout's SynthCars rows (its own calibration set) scored with the weights;
* its loss budget by **cross-validation over folds of sequences** (:func:`sensor_threshold`): the
  largest budget of a grid at which every held-out fold (2 sequences, a 40-frame street) loses at
  most ``target_lost`` of its true cars at the threshold set on the other folds;
* the threshold at that budget on all of the layout's sequences.

The table is written to the node YAML as the string parameter ``sensor_thresholds``
(``"hdl64:0.507, vlp16:0.389, ..."``; ROS 2 parameters cannot be maps), read by the node with
:func:`pcc_ros.pipeline.filter.parse_sensor_thresholds`; the node picks the entry of the preset
its beam model matches (:func:`pcc_ros.pipeline.beam_model.matching_preset`) and
``reject_threshold`` otherwise.

Measuring a layout's rows takes minutes on one CPU thread; :func:`cached_rows` keeps them on disk
keyed by the set, the measured terms and the source of the code that measures them, so rerunning
this step on another weight set costs seconds.
"""

from __future__ import annotations

import hashlib
import logging
from pathlib import Path
from typing import Any

import numpy as np

from pcc_ros.errors import ConfigError, DataError
from pcc_ros.workflows.filter_calibration import threshold_for
from pcc_ros.workflows.filter_sensors import BUDGET_GRID, Rows, synth_rows

log = logging.getLogger(__name__)

#: Source files whose code decides a measured row (a changed term invalidates the cache).
_MEASURING_CODE = ("pipeline/evidence.py", "pipeline/evidence_kernels.py", "pipeline/evidence_profile.py",
                   "pipeline/profile_kernels.py", "pipeline/filter.py", "pipeline/beam_model.py", "pipeline/core.py",
                   "geometry/beams.py", "workflows/filter_sensors.py", "workflows/detection_eval.py")


def code_fingerprint(shape: bool) -> str:
    """Hash of the code that measures a row (and whether the shape term was measured)."""
    digest = hashlib.sha256(b"shape" if shape else b"no-shape")
    package = Path(__file__).resolve().parents[1]
    for name in _MEASURING_CODE:
        digest.update((package / name).read_bytes())
    return digest.hexdigest()[:16]


def cached_rows(pipeline, root: Path, layout: str, cache: Path | None, shape: bool) -> Rows:
    """:func:`~pcc_ros.workflows.filter_sensors.synth_rows` of ``root`` (beam model ``auto``), read
    from ``cache`` when it holds them for this set and this code, else measured and stored there."""
    if cache is None:
        return synth_rows(pipeline, root, layout, "auto")
    key = hashlib.sha256(f"{Path(root).resolve()}|{layout}|{code_fingerprint(shape)}".encode()).hexdigest()[:16]
    path = Path(cache) / f"rows_{layout}_{key}.npz"
    if path.is_file():
        try:
            with np.load(path, allow_pickle=False) as z:
                rows = Rows(z["x"], z["false"], z["kind"].astype(object), z["sensor"].astype(object),
                            z["group"].astype(object))
        except (OSError, KeyError, ValueError) as exc:
            raise DataError(f"{path}: unreadable rows cache ({exc}); delete it to measure again") from exc
        log.info("rows of %s read from %s (%d rows)", layout, path, len(rows.false))
        return rows
    rows = synth_rows(pipeline, root, layout, "auto")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    np.savez(tmp, x=rows.x, false=rows.false, kind=rows.kind.astype(str), sensor=rows.sensor.astype(str),
             group=rows.group.astype(str))
    tmp.replace(path)
    return rows


def sequence_folds(group: np.ndarray, per_fold: int) -> np.ndarray:
    """Fold index of every row: its sequence's rank (sorted names) // ``per_fold``."""
    _, index = np.unique(group, return_inverse=True)
    return index // max(1, per_fold)


def sensor_threshold(p: np.ndarray, false: np.ndarray, group: np.ndarray, target_lost: float = 0.02,
                     grid: tuple[float, ...] = BUDGET_GRID, per_fold: int = 2) -> dict[str, Any]:
    """One layout's threshold for the scores ``p`` of its rows (``group``: each row's sequence).

    The budget by cross-validation over folds of ``per_fold`` sequences: each fold held out in turn,
    the threshold for each budget of ``grid`` set on the other folds, the held-out fold's true cars
    lost at it counted; the largest budget at which *every* held-out fold loses at most
    ``target_lost`` is kept (a fold of 2 SynthCars sequences of 20 frames is a street of 40 frames,
    the size of the held-out sets the promise is judged on: the pooled loss over the folds only
    tracks the budget, while one street loses more or less than another), then the threshold at
    that budget on every sequence.

    Raises :class:`ConfigError` with fewer than two folds holding true cars, or when no budget of
    ``grid`` keeps every held-out fold within ``target_lost`` (naming each budget's worst fold)."""
    true = ~false
    fold = sequence_folds(group, per_fold)
    folds = [f for f in np.unique(fold) if (true & (fold == f)).any()]
    if len(folds) < 2:
        raise ConfigError(f"per-sensor threshold: cross-validation over folds of {per_fold} sequence(s) needs two or "
                          f"more folds with true cars (have {len(folds)})")
    lost = np.zeros((len(grid), len(folds)))
    count = np.zeros(len(folds))
    for j, f in enumerate(folds):
        test, train = fold == f, fold != f
        p_test = p[test & true]
        count[j] = len(p_test)
        for i, b in enumerate(grid):
            lost[i, j] = np.count_nonzero(p_test > threshold_for(p[train], false[train], b))
    worst = (lost / count[None, :]).max(axis=1)
    pooled = lost.sum(axis=1) / count.sum()
    ok = [i for i in range(len(grid)) if worst[i] <= target_lost + 1e-12]
    if not ok:
        tried = ", ".join(f"{b:.2%}: {worst[i]:.2%}" for i, b in enumerate(grid))
        raise ConfigError(f"per-sensor threshold: no budget keeps every held-out fold's loss within {target_lost:.2%} "
                          f"(budget: worst held-out fold {tried})")
    chosen = max(ok)
    threshold = threshold_for(p, false, grid[chosen])
    return {"threshold": threshold, "budget": grid[chosen], "grid": list(grid), "folds": len(folds),
            "sequences_per_fold": per_fold, "held_out_worst_fold": worst.tolist(), "held_out_pooled": pooled.tolist(),
            "cv_worst_fold": float(worst[chosen]), "cv_pooled": float(pooled[chosen]),
            "in_sample_lost": float((p[true] > threshold).mean()),
            "in_sample_removed": float((p[false] > threshold).mean()) if false.any() else float("nan")}


def sensor_thresholds(rows_by_layout: dict[str, Rows], p_by_layout: dict[str, np.ndarray], target_lost: float = 0.02,
                      grid: tuple[float, ...] = BUDGET_GRID, per_fold: int = 2) -> dict[str, dict[str, Any]]:
    """:func:`sensor_threshold` of each layout's rows with their p_false under one rule
    (``p_by_layout``: e.g. :func:`~pcc_ros.workflows.filter_sensors.rows_probability` of a weight
    set, or the out-of-fold p_false of trees boosted on these rows)."""
    out = {}
    for layout, rows in rows_by_layout.items():
        try:
            out[layout] = sensor_threshold(p_by_layout[layout], rows.false, rows.group, target_lost, grid, per_fold)
        except ConfigError as exc:
            raise ConfigError(f"{layout}: {exc}") from None
        out[layout]["rows"] = {"true": int((~rows.false).sum()), "false": int(rows.false.sum())}
    return out


def fallback_threshold(table: dict[str, dict[str, Any]], reject_threshold: float) -> float:
    """``reject_threshold`` for a sensor that matches no preset: the largest of the layouts'
    thresholds and the weights' own (fitted to lose at most the budget on *every* calibration
    sensor), so that an unknown sensor is judged as leniently as the layout whose true cars read
    most "false" (an unknown sensor must not lose cars)."""
    return float(max([reject_threshold, *(t["threshold"] for t in table.values())]))
