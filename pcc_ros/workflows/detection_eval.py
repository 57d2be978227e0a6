"""``pcc eval detections``: does the detection filter earn its place? The yardstick.

Runs the filter node's pipeline (the same :class:`pcc_ros.pipeline.core.Pipeline` a node runs,
configured from a node YAML) over a labelled KITTI tracking / object dataset (SynthCars is
one) with a detector's results, and reports

* KITTI AP_R40 (:mod:`pcc_ros.metrics.detection`), 3D and BEV at IoU 0.7 and 0.5, easy /
  moderate / hard, of all detections (before) and of the kept ones (after);
* the operating curve — false detections removed vs true detections lost — of the filter
  and, in the same run on the same detections, of the two trivial baselines: a cut on the
  number of LiDAR points in the box and a cut on the detector score; with the share of false
  detections each removes at <= ``--max-lost`` true ones lost (best threshold, i.e. the
  baselines get an oracle threshold), and the filter's figure at its configured threshold;
* a PNG (curves, score distributions of true vs false detections) and a JSON.

A detection is *true* when its BEV IoU with a labelled box of ``--gt-classes`` or of its
KITTI neighbour classes (a Van for Car) reaches ``--true-iou``; *unknown* (left out of the
curve) when its 2D box lies mostly (> 50 % of its area) in a DontCare region; else *false*.
"""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from pcc_ros.data.kitti import read_velodyne, split_dir
from pcc_ros.data.kitti_format import Calibration, camera_to_lidar_boxes, parse_ab3dmot_lines, parse_label_lines
from pcc_ros.data.synthetic.writer import KIND_SUFFIX, read_kinds
from pcc_ros.errors import ConfigError, DataError
from pcc_ros.geometry.boxes import iou_bev, points_in_boxes
from pcc_ros.metrics.detection import DIFFICULTIES, NEIGHBOURS, FrameBoxes, ap_table
from pcc_ros.pipeline.config import CONFIG_FILES, shipped_config_dir
from pcc_ros.pipeline.core import Pipeline, PipelineConfig
from pcc_ros.pipeline.filter import TERMS, FilterConfig
from pcc_ros.plotting import operating_curves
from pcc_ros.types import Boxes, class_mask

log = logging.getLogger(__name__)

def default_config() -> Path:
    """The filter node's shipped parameter file: ``config/`` of a checkout, or
    ``share/pcc_ros/config`` of an install (found as the nodes find it,
    :func:`pcc_ros.pipeline.config.shipped_config_dir`)."""
    return shipped_config_dir() / CONFIG_FILES["filter"]


# ----------------------------------------------------------------------------- data


class LabelledFrame:
    """One scan with labelled ground truth and detections (LiDAR frame, KITTI attributes);
    ``rings``: the scan's ring field when its source has one (nuScenes, AV2), for the filter's
    beam model (``sensor: auto``)."""

    def __init__(self, name: str, points: np.ndarray, gt: FrameBoxes, dt: FrameBoxes, dontcare: np.ndarray,
                 rings: np.ndarray | None = None, kinds: np.ndarray | None = None):
        self.name, self.points, self.gt, self.dt, self.dontcare = name, points, gt, dt, dontcare
        self.rings = rings
        #: SynthCars' label of each detection ("true" or a false-positive kind), None for other data.
        self.kinds = kinds


def _rows_to_frameboxes(rows, calib: Calibration, name: str) -> tuple[FrameBoxes, np.ndarray]:
    care = np.array([t != "DontCare" for t in rows.type], dtype=bool)
    dontcare = rows.bbox[~care]
    rows = rows[care]
    boxes = camera_to_lidar_boxes(rows, calib)
    return FrameBoxes(boxes, rows.bbox, rows.truncated, rows.occluded, name), dontcare


def _read_lines(path: Path) -> list[str]:
    try:
        return path.read_text().splitlines()
    except OSError as exc:
        raise DataError(f"{path}: cannot read ({exc.strerror})") from exc


def load_kitti(
    root: str | Path, detections: str | Path | None, sequence: str | None = None, frames: slice = slice(None)
) -> list[LabelledFrame]:
    """Frames of a KITTI tracking sequence (``label_02``) or of the object set (``label_2``).

    ``root`` may hold ``training/`` or be the split directory. Detection files: KITTI object
    lines with a score column, ``DETECTIONS/FFFFFF.txt`` or ``DETECTIONS/SSSS/FFFFFF.txt``; or
    AB3DMOT's one file per tracking sequence, ``DETECTIONS/SSSS.txt``.
    A frame without a detection file reads as no detections (counted, logged).
    """
    split = split_dir(Path(root), "training")
    det_root = None if detections is None else Path(detections)
    if det_root is not None and not det_root.is_dir():
        raise DataError(f"{det_root}: detections directory does not exist")
    out: list[LabelledFrame] = []
    missing = 0
    if (split / "label_02").is_dir():
        sequences = sorted(p.name for p in (split / "velodyne").iterdir() if p.is_dir())
        if sequence is None:
            if len(sequences) != 1:
                raise ConfigError(f"{split}: several sequences ({', '.join(sequences)}); pass --sequence")
            sequence = sequences[0]
        if sequence not in sequences:
            raise DataError(f"{split}: no sequence {sequence!r} (have {', '.join(sequences)})")
        calib = Calibration.read(split / "calib" / f"{sequence}.txt")
        label_path = split / "label_02" / f"{sequence}.txt"
        rows = parse_label_lines(_read_lines(label_path), tracking=True, source=str(label_path))
        det_dir = None if det_root is None else det_root / sequence if (det_root / sequence).is_dir() else det_root
        per_sequence = None  # AB3DMOT's published layout: one comma-separated file per sequence
        if det_dir is det_root and det_root is not None and (det_root / f"{sequence}.txt").is_file():
            path = det_root / f"{sequence}.txt"
            per_sequence = parse_ab3dmot_lines(_read_lines(path), source=str(path))
        for scan in sorted((split / "velodyne" / sequence).glob("*.bin"))[frames]:
            index = int(scan.stem)
            gt, dontcare = _rows_to_frameboxes(rows[rows.frame == index], calib, f"{sequence}/{scan.stem}")
            if per_sequence is not None:  # a frame without a line has no detections
                dt, found = _rows_to_frameboxes(per_sequence[per_sequence.frame == index], calib, scan.stem)[0], True
            else:
                dt, found = _read_detections(None if det_dir is None else det_dir / f"{scan.stem}.txt", calib)
            missing += not found and det_dir is not None
            kinds = _read_kinds(None if det_dir is None else det_dir / f"{scan.stem}.txt", len(dt.boxes))
            out.append(LabelledFrame(f"{sequence}/{scan.stem}", read_velodyne(scan), gt, dt, dontcare, kinds=kinds))
    elif (split / "label_2").is_dir():
        for scan in sorted((split / "velodyne").glob("*.bin"))[frames]:
            calib = Calibration.read(split / "calib" / f"{scan.stem}.txt")
            label_path = split / "label_2" / f"{scan.stem}.txt"
            rows = parse_label_lines(_read_lines(label_path), tracking=False, source=str(label_path))
            gt, dontcare = _rows_to_frameboxes(rows, calib, scan.stem)
            dt, found = _read_detections(None if det_root is None else det_root / f"{scan.stem}.txt", calib)
            missing += not found and det_root is not None
            kinds = _read_kinds(None if det_root is None else det_root / f"{scan.stem}.txt", len(dt.boxes))
            out.append(LabelledFrame(scan.stem, read_velodyne(scan), gt, dt, dontcare, kinds=kinds))
    else:
        raise DataError(f"{split}: neither label_02/ (tracking) nor label_2/ (object) found")
    if missing:
        log.warning("%d frame(s) had no detection file in %s (read as no detections)", missing, det_root)
    if not out:
        raise DataError(f"{split}: no scans selected")
    return out


def _read_kinds(path: Path | None, count: int) -> np.ndarray | None:
    """SynthCars' per-detection kinds beside a detection file (``FFFFFF.kind``), if any."""
    if path is None:
        return None
    read = read_kinds(path.with_suffix(KIND_SUFFIX), count)
    return None if read is None else read[0]


def _read_detections(path: Path | None, calib: Calibration) -> tuple[FrameBoxes, bool]:
    if path is None or not path.exists():
        return FrameBoxes(Boxes.empty()), False
    rows = parse_label_lines(_read_lines(path), tracking=False, source=str(path))
    fb, _ = _rows_to_frameboxes(rows, calib, path.stem)
    return fb, True


# ----------------------------------------------------------------------------- truth


def detection_truth(
    frame: LabelledFrame, gt_classes: tuple[str, ...], true_iou: float
) -> np.ndarray:
    """Per detection: 1 true, 0 false, -1 unknown (in a DontCare region)."""
    names = {c.lower() for c in gt_classes}
    for c in list(names):
        names |= set(NEIGHBOURS.get(c, ()))
    dt = frame.dt.boxes
    gt = frame.gt.boxes[class_mask(frame.gt.boxes.label, tuple(names))]
    truth = np.zeros(len(dt), dtype=np.int64)
    if len(gt) and len(dt):
        truth[iou_bev(dt, gt).max(axis=1) >= true_iou] = 1
    if len(frame.dontcare) and len(dt):
        box = frame.dt.bbox
        area = np.maximum(box[:, 2] - box[:, 0], 0) * np.maximum(box[:, 3] - box[:, 1], 0)
        dc = frame.dontcare
        iw = np.clip(np.minimum(box[:, None, 2], dc[None, :, 2]) - np.maximum(box[:, None, 0], dc[None, :, 0]), 0, None)
        ih = np.clip(np.minimum(box[:, None, 3], dc[None, :, 3]) - np.maximum(box[:, None, 1], dc[None, :, 1]), 0, None)
        inside = (iw * ih).max(axis=1) / np.maximum(area, 1e-9)
        truth[(truth == 0) & (inside > 0.5)] = -1
    return truth


# ----------------------------------------------------------------------------- curves


def operating_curve(false_score: np.ndarray, is_true: np.ndarray) -> dict[str, np.ndarray]:
    """Removing every detection whose ``false_score`` exceeds a threshold, for every threshold:
    share of false detections removed and of true ones lost (``thresholds`` descending; the
    first point removes nothing)."""
    s = np.asarray(false_score, dtype=np.float64)
    t = np.asarray(is_true, dtype=bool)
    values = np.unique(s[np.isfinite(s)])[::-1]
    thresholds = np.r_[np.inf, values] if len(values) else np.array([np.inf])
    # remove where s >= threshold (threshold = a value in the data)
    removed = (s[None, :] >= thresholds[:, None]) & np.isfinite(s)[None, :]
    n_true, n_false = max(int(t.sum()), 1), max(int((~t).sum()), 1)
    return {
        "threshold": thresholds,
        "false_removed": removed[:, ~t].sum(axis=1) / n_false,
        "true_lost": removed[:, t].sum(axis=1) / n_true,
    }


def removed_at(curve: dict[str, np.ndarray], max_lost: float) -> tuple[float, float]:
    """(best share of false removed with at most ``max_lost`` true lost, the threshold)."""
    ok = curve["true_lost"] <= max_lost + 1e-12
    i = int(np.argmax(np.where(ok, curve["false_removed"], -1.0)))
    return float(curve["false_removed"][i]), float(curve["threshold"][i])


def auc(false_score: np.ndarray, is_true: np.ndarray) -> float:
    """P(a false detection scores higher than a true one), ties half: 0.5 is chance."""
    s, t = np.asarray(false_score, float), np.asarray(is_true, bool)
    f, tr = s[~t], s[t]
    if not len(f) or not len(tr):
        return float("nan")
    return float(((f[:, None] > tr[None, :]).sum() + 0.5 * (f[:, None] == tr[None, :]).sum()) / (len(f) * len(tr)))


def compare(p_false: np.ndarray, points: np.ndarray, is_true: np.ndarray, group: np.ndarray, status: np.ndarray,
            max_lost: float) -> dict[str, Any]:
    """The filter's and the points-in-box count's operating points and per-group removal.

    ``at_loss``: the share of each false group each method removes at its best threshold that
    loses at most ``max_lost`` of the true boxes (an oracle threshold for both, same loss
    budget); ``configured``: what the filter's configured threshold removed and lost."""
    methods = {"filter": p_false, "points-in-box": -points.astype(np.float64)}
    out: dict[str, Any] = {"true": int(is_true.sum()), "false": int((~is_true).sum()), "methods": {}}
    groups = sorted(set(group[~is_true]))
    for name, s in methods.items():
        curve = operating_curve(s, is_true)
        removed, threshold = removed_at(curve, max_lost)
        cut = s >= threshold
        out["methods"][name] = {
            f"false_removed_at_{max_lost:g}_lost": removed,
            "threshold": threshold if name == "filter" else -threshold,
            "auc_false_above_true": auc(s, is_true),
            "per_group_removed": {g: float(cut[group == g].mean()) for g in groups},
            "curve": curve,
        }
    rejected = status == "rejected"
    out["configured"] = {
        "false_removed": float(rejected[~is_true].mean()) if (~is_true).any() else float("nan"),
        "true_lost": float(rejected[is_true].mean()) if is_true.any() else float("nan"),
        "true_lost_count": int(rejected[is_true].sum()),
        "per_group_removed": {g: float(rejected[group == g].mean()) for g in groups},
        "per_group_count": {g: int((group == g).sum()) for g in groups},
        "unjudged": int((~np.isin(status, ("kept", "rejected"))).sum()),
    }
    return out



# ----------------------------------------------------------------------------- run


def run_filter(frames: list[LabelledFrame], pipeline, progress: bool = True) -> list[dict[str, Any]]:
    """The pipeline's per-detection outputs for every frame (status, p_false, terms, points in box)."""
    out = []
    for frame in tqdm(frames, desc="filter", unit="frame", disable=not progress):
        result = pipeline.process(frame.points, frame.dt.boxes, frame_id="velodyne", rings=frame.rings)
        counts = np.array([len(i) for i in points_in_boxes(frame.points, frame.dt.boxes)], dtype=np.int64)
        out.append(
            {
                "status": result.status,
                "p_false": result.filter_score if result.filter_score is not None else np.full(len(counts), np.nan),
                "mismatch": result.mismatch,
                "terms": result.filter_terms,
                "points": counts,
                "timings_ms": result.timings_ms,
            }
        )
    return out


def evaluate_detections(
    frames: list[LabelledFrame],
    pipeline,
    gt_classes: tuple[str, ...] = ("Car",),
    true_iou: float = 0.3,
    max_lost: float = 0.02,
    progress: bool = True,
) -> dict[str, Any]:
    """AP before / after and the operating curves of the filter and the baselines (a dict)."""
    results = run_filter(frames, pipeline, progress)
    truth = np.concatenate([detection_truth(f, gt_classes, true_iou) for f in frames]) if frames else np.zeros(0)
    status = np.concatenate([r["status"] for r in results])
    rejected = status == "rejected"
    p_false = np.concatenate([r["p_false"] for r in results])
    points = np.concatenate([r["points"] for r in results])
    scores = np.concatenate([f.dt.boxes.score for f in frames])
    rule = pipeline.config.filter.rule
    if rule == "evidence":
        filter_score = p_false
    else:
        mismatch = np.concatenate([r["mismatch"] for r in results])
        filter_score = np.where(np.isfinite(mismatch), mismatch, -np.inf)  # unjudged: never removed
    known = truth >= 0
    is_true = truth[known] == 1
    methods = {
        "filter": filter_score[known],
        "points-in-box": -points[known].astype(np.float64),
        "detector score": -scores[known],
    }
    curves = {name: operating_curve(s, is_true) for name, s in methods.items()}
    table = {}
    for name, curve in curves.items():
        removed, threshold = removed_at(curve, max_lost)
        table[name] = {
            f"false_removed_at_{max_lost:g}_lost": removed,
            "threshold": threshold if name == "filter" else -threshold,
            "auc_false_above_true": auc(methods[name], is_true),
        }
    per_kind = None
    if frames and all(f.kinds is not None for f in frames):
        kinds = np.concatenate([f.kinds for f in frames])[known]
        per_kind = compare(filter_score[known], points[known], kinds == "true", kinds, status[known], max_lost)
    n_true, n_false = int(is_true.sum()), int((~is_true).sum())
    shipped = {
        "true_kept": int((~rejected[known] & is_true).sum()),
        "true_lost": int((rejected[known] & is_true).sum()),
        "false_kept": int((~rejected[known] & ~is_true).sum()),
        "false_removed": int((rejected[known] & ~is_true).sum()),
    }
    shipped["false_removed_share"] = shipped["false_removed"] / max(n_false, 1)
    shipped["true_lost_share"] = shipped["true_lost"] / max(n_true, 1)
    shipped["precision_before"] = n_true / max(n_true + n_false, 1)
    shipped["precision_after"] = shipped["true_kept"] / max(shipped["true_kept"] + shipped["false_kept"], 1)
    gts = [f.gt for f in frames]
    before = [f.dt for f in frames]
    after = [f.dt.subset(r["status"] != "rejected") for f, r in zip(frames, results)]
    ap_before = ap_table(gts, before, "Car", gt_classes=gt_classes)
    ap_after = ap_table(gts, after, "Car", gt_classes=gt_classes)
    filter_ms = [r["timings_ms"].get("filter_ms", 0.0) for r in results]
    complete_ms = [r["timings_ms"].get("complete_ms", 0.0) for r in results]
    return {
        "frames": len(frames),
        "detections": len(truth),
        "true": n_true,
        "false": n_false,
        "unknown": int((truth < 0).sum()),
        "gt_classes": list(gt_classes),
        "true_iou": true_iou,
        "max_lost": max_lost,
        "rule": rule,
        "filter_config": {k: getattr(pipeline.config.filter, k) for k in pipeline.config.filter.__dataclass_fields__},
        "threshold_in_force": threshold_in_force_json(pipeline.threshold_in_force),
        "shipped_threshold": shipped,
        "operating_points": table,
        "per_kind": None if per_kind is None else _without_curves(per_kind),
        "ap_before": ap_before,
        "ap_after": ap_after,
        "filter_ms_mean": float(np.mean(filter_ms)) if filter_ms else 0.0,
        "complete_ms_mean": float(np.mean(complete_ms)) if complete_ms else 0.0,
        "_curves": curves,
        "_scores": {
            "p_false": filter_score[known],
            "is_true": is_true,
            "terms": _stack_terms([r["terms"] for r in results], known),
        },
    }


def _without_curves(table: dict[str, Any]) -> dict[str, Any]:
    """A :func:`compare` table without its curve arrays (for the JSON)."""
    out = dict(table)
    out["methods"] = {k: {kk: vv for kk, vv in v.items() if kk != "curve"} for k, v in table["methods"].items()}
    return out


def print_groups(table: dict[str, Any], what: str) -> None:
    """The per-group removal of a :func:`compare` table as a Markdown table."""
    max_key = next(k for k in next(iter(table["methods"].values())) if k.startswith("false_removed_at_"))
    methods = table["methods"]
    conf = table["configured"]
    print(f"\n| {what} | boxes | filter, configured | filter at the loss budget | points-in-box at the same budget |")
    print("| --- | --- | --- | --- | --- |")
    for g, n in conf["per_group_count"].items():
        print(f"| {g} | {n} | {conf['per_group_removed'][g]:.1%} | {methods['filter']['per_group_removed'][g]:.1%} | "
              f"{methods['points-in-box']['per_group_removed'][g]:.1%} |")
    print(f"| all false | {table['false']} | {conf['false_removed']:.1%} | {methods['filter'][max_key]:.1%} | "
          f"{methods['points-in-box'][max_key]:.1%} |")
    print(f"true lost at the configured threshold: {conf['true_lost_count']} / {table['true']} "
          f"({conf['true_lost']:.1%}); {max_key.replace('_', ' ')} budget")


def _stack_terms(terms: list[dict[str, np.ndarray]], known: np.ndarray) -> dict[str, np.ndarray]:
    names = sorted({k for t in terms for k in t})
    out = {}
    for k in names:
        parts = [t.get(k) for t in terms]
        if any(p is None for p in parts):
            continue
        out[k] = np.concatenate(parts)[known]
    return out


# ----------------------------------------------------------------------------- output


def print_report(results: dict[str, Any], title: str) -> None:
    max_lost = results["max_lost"]
    print(f"\n{title}: {results['frames']} frames, {results['detections']} detections "
          f"({results['true']} true, {results['false']} false, {results['unknown']} in DontCare regions)")
    classes = results["gt_classes"]
    print("\nKITTI AP_R40 (%), Car" + (f" (counting {'+'.join(classes)})" if len(classes) > 1 else ""))
    print(f"| {'metric':<9} | " + " | ".join(f"{d:>17}" for d in DIFFICULTIES) + " |")
    print("| --- | " + " | ".join("---" for _ in DIFFICULTIES) + " |")
    for key in results["ap_before"]:
        cells = []
        for d in DIFFICULTIES:
            b, a = results["ap_before"][key][d], results["ap_after"][key][d]
            cells.append(f"{b:6.2f} -> {a:6.2f}")
        print(f"| {key:<9} | " + " | ".join(f"{c:>17}" for c in cells) + " |")
    print(f"\nOperating curve: false detections removed at <= {max_lost:.0%} true lost (best threshold)")
    print("| method | false removed | threshold | P(false scores above true) |")
    print("| --- | --- | --- | --- |")
    for name, row in results["operating_points"].items():
        print(f"| {name} | {row[f'false_removed_at_{max_lost:g}_lost']:.1%} | {row['threshold']:.3g} | "
              f"{row['auc_false_above_true']:.3f} |")
    if results.get("per_kind"):
        print_groups(results["per_kind"], "false-positive kind (SynthCars labels)")
    s = results["shipped_threshold"]
    print(f"\nConfigured filter ({results['rule']} rule): removes {s['false_removed']}/{results['false']} false "
          f"({s['false_removed_share']:.1%}), loses {s['true_lost']}/{results['true']} true "
          f"({s['true_lost_share']:.1%}); precision {s['precision_before']:.3f} -> {s['precision_after']:.3f}; "
          f"filter {results['filter_ms_mean']:.1f} ms/frame vs completion {results['complete_ms_mean']:.1f} ms/frame")
    print_threshold_in_force(results.get("threshold_in_force"))


def threshold_in_force_json(in_force: tuple[str | None, float] | None) -> dict[str, Any] | None:
    """The evidence rule's ``(preset, threshold)`` in force (:attr:`Pipeline.threshold_in_force`) as
    the result JSONs of ``pcc eval detections`` carry it (None: no box was judged by that rule)."""
    return None if in_force is None else {"preset": in_force[0], "threshold": in_force[1]}


def print_threshold_in_force(force: dict[str, Any] | None) -> None:
    """One line: the reject threshold the evidence rule used, and the preset the beam model matched."""
    if force:
        print(f"reject threshold in force {force['threshold']:.4f} (beam model matched preset: "
              f"{force['preset'] or 'none'})")


def plot(results: dict[str, Any], path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scores = results["_scores"]
    # the terms the configured rule reads (weights and trees; the score too: a baseline), the ray terms first
    config = results["filter_config"]
    weighted = set(FilterConfig(**config).weighted_terms) | {"density", "free_space", "ground_gap", "score"}
    terms = [t for t in TERMS if t in scores["terms"] and t in weighted]
    cols = 3
    rows = int(np.ceil((2 + len(terms)) / cols))
    fig, grid = plt.subplots(rows, cols, figsize=(5 * cols, 4.2 * rows), squeeze=False)
    axes = grid.ravel()
    for extra in axes[2 + len(terms):]:
        extra.axis("off")
    s = results["shipped_threshold"]
    operating_curves(axes[0], results["_curves"], (s["true_lost_share"], s["false_removed_share"]),
                     results["max_lost"], "true detections", "false detections", (-1, 30))
    is_true = scores["is_true"]
    panels = [("p_false" if results["rule"] == "evidence" else "mismatch", scores["p_false"])]
    panels += [(t, scores["terms"][t]) for t in terms]
    for ax, (name, values) in zip(axes[1:], panels):
        finite = np.isfinite(values)
        bins = np.linspace(np.min(values[finite]), np.max(values[finite]), 25) if finite.any() else 10
        ax.hist(values[finite & is_true], bins=bins, alpha=0.6, label=f"true ({int((finite & is_true).sum())})")
        ax.hist(values[finite & ~is_true], bins=bins, alpha=0.6, label=f"false ({int((finite & ~is_true).sum())})")
        ax.set_title(name)
        ax.legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout(rect=(0, 0, 1, 1 - 0.25 / (4.2 * rows)))  # room for the title over the top row
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def to_json(results: dict[str, Any]) -> dict[str, Any]:
    """The results without the arrays kept for the plot; write with ``files.write_json(...,
    nonfinite_null=True)`` (an undefined AP or curve point is ``null``)."""
    out = {k: v for k, v in results.items() if not k.startswith("_")}
    out["curves"] = results["_curves"]
    return out


# ----------------------------------------------------------------------------- CLI


def parse_frames(text: str | None) -> slice:
    if not text:
        return slice(None)
    try:
        a, _, b = text.partition(":")
        return slice(int(a) if a else None, int(b) if b else None)
    except ValueError as exc:
        raise ConfigError(f"--frames must be START:STOP, got {text!r}") from exc


def build_pipeline(config_path: Path | None, overrides: dict[str, Any]):
    config = PipelineConfig.from_yaml(config_path or default_config())
    main = {k: v for k, v in overrides.items() if k in ("backend", "checkpoint", "device") and v is not None}
    filt = {k: v for k, v in overrides.items() if k not in main and v is not None}
    if filt:
        config = replace(config, filter=replace(config.filter, **filt))
    if main:
        config = replace(config, **main)
    pipeline = Pipeline(config)
    pipeline.all_terms = True  # the checks and calibration report every term, weighted or not
    return pipeline
