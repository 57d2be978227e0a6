"""KITTI-style 3D / BEV detection average precision (AP with 40-point interpolation).

A line-by-line port of the KITTI object benchmark's Python evaluation as shipped with
OpenPCDet / SECOND (``kitti_object_eval_python/eval.py``: ``clean_data``,
``compute_statistics_jit``, ``get_thresholds``, ``get_mAP_R40``), with the rotated IoUs of
:mod:`pcc_ros.geometry.boxes` (computed in the LiDAR frame; KITTI computes them in the
rectified camera frame, which differs from it by a rigid motion, so the IoUs agree to the
calibration's tilt).

Rules, per evaluated class ``cls`` and difficulty (easy / moderate / hard):

* ground truth: a box of ``cls`` is *valid* when its 2D image box is taller than
  ``MIN_HEIGHT``, its occlusion level is at most ``MAX_OCCLUSION`` and its truncation at most
  ``MAX_TRUNCATION`` for the difficulty; a box of ``cls`` that fails these, or of a
  *neighbour* class (``Van`` for ``Car``), is *ignored*: it may absorb one detection, which
  then counts neither as true nor as false positive; other classes do not exist for ``cls``.
* detections of ``cls`` whose 2D box is lower than ``MIN_HEIGHT`` are ignored the same way
  (detections without a 2D box — a bag, a ROS topic — are never ignored for height).
* DontCare regions only matter for the 2D metric in KITTI's Python evaluation, not for
  BEV / 3D: none here.
* score thresholds: the scores of the true positives found by greedy best-score matching at
  ``min_overlap``, thinned to 41 recall sample points; precision at each threshold with
  max-overlap matching; precision made monotone; AP_R40 = mean of samples 1..40, in percent.

``gt_classes`` lets a dataset without ``Car`` labels (KITTI tracking 0000 frames 0-19 holds
only ``Van``\\ s) be scored as one vehicle class: every name in it counts as ``cls``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from pcc_ros.errors import DataError
from pcc_ros.geometry.boxes import iou_3d, iou_bev
from pcc_ros.types import Boxes

DIFFICULTIES = ("easy", "moderate", "hard")
MIN_HEIGHT = (40.0, 25.0, 25.0)  # pixels
MAX_OCCLUSION = (0, 1, 2)
MAX_TRUNCATION = (0.15, 0.3, 0.5)
#: KITTI's neighbour classes: ignored (not false) when evaluating the key class.
NEIGHBOURS = {"car": ("van",), "pedestrian": ("person_sitting",)}
N_SAMPLE_PTS = 41
METRICS = ("3d", "bev")


@dataclass
class FrameBoxes:
    """One frame's ground truth or detections with the KITTI attributes the rules need.

    ``bbox`` is the ``(N, 4)`` 2D image box (x1, y1, x2, y2), NaN rows where unknown;
    ``truncated`` / ``occluded`` matter for ground truth only.
    """

    boxes: Boxes
    bbox: np.ndarray | None = None
    truncated: np.ndarray | None = None
    occluded: np.ndarray | None = None
    frame: str = ""
    extras: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        n = len(self.boxes)
        self.bbox = np.full((n, 4), np.nan) if self.bbox is None else np.asarray(self.bbox, float).reshape(n, 4)
        self.truncated = np.zeros(n) if self.truncated is None else np.asarray(self.truncated, float).reshape(n)
        self.occluded = np.zeros(n) if self.occluded is None else np.asarray(self.occluded, float).reshape(n)

    def __len__(self) -> int:
        return len(self.boxes)

    def subset(self, mask: np.ndarray) -> FrameBoxes:
        return FrameBoxes(self.boxes[mask], self.bbox[mask], self.truncated[mask], self.occluded[mask], self.frame)


def _names(labels: np.ndarray) -> np.ndarray:
    return np.array([str(v).lower().rsplit(".", 1)[-1] for v in labels], dtype=object)


def clean_data(
    gt: FrameBoxes, dt: FrameBoxes, cls: str, difficulty: int, gt_classes: Sequence[str] | None = None
) -> tuple[int, np.ndarray, np.ndarray]:
    """KITTI ``clean_data``: (number of valid ground truths, ignored_gt, ignored_dt).

    Codes: 0 valid, 1 ignored (may absorb a detection), -1 not this class.
    """
    key = cls.lower()
    positives = {key, *(c.lower() for c in (gt_classes or ()))}
    neighbours = set(NEIGHBOURS.get(key, ())) - positives
    names = _names(gt.boxes.label)
    height = gt.bbox[:, 3] - gt.bbox[:, 1]
    hard = (
        (gt.occluded > MAX_OCCLUSION[difficulty])
        | (gt.truncated > MAX_TRUNCATION[difficulty])
        | (height <= MIN_HEIGHT[difficulty])  # NaN height: not <=, never "too small"
    )
    positive = np.array([n in positives for n in names], dtype=bool)
    neighbour = np.array([n in neighbours for n in names], dtype=bool)
    ignored_gt = np.where(positive & ~hard, 0, np.where(neighbour | (positive & hard), 1, -1))
    dnames = _names(dt.boxes.label)
    dheight = np.abs(dt.bbox[:, 3] - dt.bbox[:, 1])
    dpositive = np.array([n in positives for n in dnames], dtype=bool)
    ignored_dt = np.where(dheight < MIN_HEIGHT[difficulty], 1, np.where(dpositive, 0, -1))
    return int((ignored_gt == 0).sum()), ignored_gt.astype(np.int64), ignored_dt.astype(np.int64)


def compute_statistics(
    overlaps: np.ndarray,
    scores: np.ndarray,
    ignored_gt: np.ndarray,
    ignored_dt: np.ndarray,
    min_overlap: float,
    thresh: float = 0.0,
    compute_fp: bool = False,
) -> tuple[int, int, int, np.ndarray]:
    """KITTI ``compute_statistics_jit`` for one frame: (tp, fp, fn, scores of the true positives).

    ``overlaps``: ``(n_dt, n_gt)``. A loop over boxes (tens per frame), not points: the greedy
    matching is sequential by definition.
    """
    n_dt, n_gt = overlaps.shape
    assigned = np.zeros(n_dt, dtype=bool)
    below = scores < thresh if compute_fp else np.zeros(n_dt, dtype=bool)
    no_det = -10000000.0
    tp = fp = fn = 0
    tp_scores = []
    for i in range(n_gt):
        if ignored_gt[i] == -1:
            continue
        det_idx, valid, max_overlap, assigned_ignored = -1, no_det, 0.0, False
        for j in range(n_dt):
            if ignored_dt[j] == -1 or assigned[j] or below[j]:
                continue
            overlap = overlaps[j, i]
            if not compute_fp and overlap > min_overlap and scores[j] > valid:
                det_idx, valid = j, scores[j]
            elif (
                compute_fp and overlap > min_overlap and (overlap > max_overlap or assigned_ignored)
                and ignored_dt[j] == 0
            ):
                max_overlap, det_idx, valid, assigned_ignored = overlap, j, 1.0, False
            elif compute_fp and overlap > min_overlap and valid == no_det and ignored_dt[j] == 1:
                det_idx, valid, assigned_ignored = j, 1.0, True
        if valid == no_det and ignored_gt[i] == 0:
            fn += 1
        elif valid != no_det and (ignored_gt[i] == 1 or ignored_dt[det_idx] == 1):
            assigned[det_idx] = True
        elif valid != no_det:
            tp += 1
            tp_scores.append(scores[det_idx])
            assigned[det_idx] = True
    if compute_fp:
        fp = int((~(assigned | (ignored_dt == -1) | (ignored_dt == 1) | below)).sum())
    return tp, fp, fn, np.asarray(tp_scores, dtype=np.float64)


def get_thresholds(scores: np.ndarray, num_gt: int, num_sample_pts: int = N_SAMPLE_PTS) -> np.ndarray:
    """KITTI ``get_thresholds``: true-positive scores thinned to the recall sample points."""
    scores = np.sort(np.asarray(scores, dtype=np.float64))[::-1]
    current, out = 0.0, []
    for i, score in enumerate(scores):
        left = (i + 1) / num_gt
        right = (i + 2) / num_gt if i < len(scores) - 1 else left
        if (right - current) < (current - left) and i < len(scores) - 1:
            continue
        out.append(score)
        current += 1.0 / (num_sample_pts - 1.0)
    return np.asarray(out, dtype=np.float64)


def overlaps_for(metric: str, dt: Boxes, gt: Boxes) -> np.ndarray:
    """``(n_dt, n_gt)`` rotated IoU: ``"3d"`` or ``"bev"``."""
    if metric not in METRICS:
        raise DataError(f"unknown detection metric {metric!r} (have {METRICS})")
    if len(dt) == 0 or len(gt) == 0:
        return np.zeros((len(dt), len(gt)))
    return iou_3d(dt, gt) if metric == "3d" else iou_bev(dt, gt)


@dataclass
class APResult:
    ap: float  # percent; NaN without a valid ground truth
    num_gt: int
    precision: np.ndarray  # (41,) interpolated precision at the sampled thresholds
    recall: np.ndarray  # (41,)
    thresholds: np.ndarray


def average_precision(
    gts: Sequence[FrameBoxes],
    dts: Sequence[FrameBoxes],
    cls: str = "Car",
    metric: str = "3d",
    min_overlap: float = 0.7,
    difficulty: int = 1,
    gt_classes: Sequence[str] | None = None,
    overlaps: Sequence[np.ndarray] | None = None,
) -> APResult:
    """AP_R40 (percent) of one class / metric / IoU / difficulty over a list of frames.

    ``overlaps`` (one ``(n_dt, n_gt)`` per frame) may be passed to share IoUs between calls.
    """
    if len(gts) != len(dts):
        raise DataError(f"{len(gts)} ground-truth frames but {len(dts)} detection frames")
    if overlaps is None:
        overlaps = [overlaps_for(metric, d.boxes, g.boxes) for g, d in zip(gts, dts)]
    cleaned = [clean_data(g, d, cls, difficulty, gt_classes) for g, d in zip(gts, dts)]
    num_gt = sum(c[0] for c in cleaned)
    precision = np.zeros(N_SAMPLE_PTS)
    recall = np.zeros(N_SAMPLE_PTS)
    if num_gt == 0:
        return APResult(float("nan"), 0, precision, recall, np.zeros(0))
    tp_scores = [
        compute_statistics(o, d.boxes.score, c[1], c[2], min_overlap)[3] for o, d, c in zip(overlaps, dts, cleaned)
    ]
    thresholds = get_thresholds(np.concatenate(tp_scores) if tp_scores else np.zeros(0), num_gt)[:N_SAMPLE_PTS]
    pr = np.zeros((len(thresholds), 3))
    for o, d, c in zip(overlaps, dts, cleaned):
        for t, thresh in enumerate(thresholds):
            tp, fp, fn, _ = compute_statistics(o, d.boxes.score, c[1], c[2], min_overlap, thresh, compute_fp=True)
            pr[t] += (tp, fp, fn)
    k = len(thresholds)
    recall[:k] = pr[:, 0] / np.maximum(pr[:, 0] + pr[:, 2], 1e-12)
    precision[:k] = pr[:, 0] / np.maximum(pr[:, 0] + pr[:, 1], 1e-12)
    precision[:k] = np.maximum.accumulate(precision[:k][::-1])[::-1]
    ap = float(precision[1:].sum() / (N_SAMPLE_PTS - 1) * 100.0)
    return APResult(ap, int(num_gt), precision, recall, thresholds)


def ap_table(
    gts: Sequence[FrameBoxes],
    dts: Sequence[FrameBoxes],
    cls: str = "Car",
    overlaps_at: Sequence[float] = (0.7, 0.5),
    gt_classes: Sequence[str] | None = None,
) -> dict[str, dict[str, float]]:
    """``{"3d@0.7": {"easy": AP, "moderate": AP, "hard": AP}, "bev@0.7": ..., ...}`` (percent)."""
    out: dict[str, dict[str, float]] = {}
    for metric in METRICS:
        shared = [overlaps_for(metric, d.boxes, g.boxes) for g, d in zip(gts, dts)]
        for iou in overlaps_at:
            out[f"{metric}@{iou:g}"] = {
                name: average_precision(gts, dts, cls, metric, iou, k, gt_classes, shared).ap
                for k, name in enumerate(DIFFICULTIES)
            }
    return out
