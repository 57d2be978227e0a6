"""A detector's recall against the returns on each labelled car: the simulated detector beside a real one.

The filter's threshold must spare every true detection it is likely to see, so how sparse the
true detections of the simulated detector are (``pcc_ros/data/synthetic/detector.py``: detected
with probability ``1 - exp(-returns / 12)``) decides what the calibration learns. This module
measures, on any KITTI-layout root with a detector's results (real PointRCNN on KITTI tracking,
or a SynthCars root whose ``.kind`` files mark its true detections):

* per labelled car (the ``gt_classes`` labels), its **returns**: scan points inside the labelled
  box more than :data:`BODY_MARGIN` above its bottom (ground returns under the wheels left out,
  as the filter's terms leave them out), and whether a detection matches it (BEV IoU >=
  ``true_iou``; on SynthCars only its ``true`` detections count, a misplaced box is no detection
  of the car);
* **recall by returns** (:data:`RETURN_BINS`) and by range (:data:`RANGE_BINS`);
* the **true detections' returns by range**: the share with fewer than 5 / 10 / 20.

``python -m pcc_ros.workflows.detector_recall --kitti ROOT --detections DIR [--kitti ...] --json OUT --plot PNG``
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path
from typing import Any

import numpy as np

from pcc_ros.files import write_json
from pcc_ros.geometry.boxes import iou_bev, points_in_boxes
from pcc_ros.types import class_mask
from pcc_ros.workflows.detection_eval import LabelledFrame, load_kitti

log = logging.getLogger(__name__)

#: Metres above a labelled box's bottom below which returns are ground, not car.
BODY_MARGIN = 0.15
#: Bins of returns per labelled car (lower edges; the last bin is open).
RETURN_BINS = (0, 1, 5, 10, 20, 50, 100)
#: Range bins, metres (lower edges; the last bin is open).
RANGE_BINS = (0.0, 20.0, 40.0)
#: Bins with fewer labelled cars than this are drawn hollow.
FEW = 5
#: "Fewer than" cuts of the true detections' returns.
SPARSE_CUTS = (5, 10, 20)


def car_rows(frames: list[LabelledFrame], gt_classes: tuple[str, ...] = ("Car", "Van"),
             true_iou: float = 0.3) -> dict[str, np.ndarray]:
    """Per labelled car of ``frames``: ``returns``, ``range`` (m, bird's-eye view) and ``detected``."""
    returns, ranges, detected = [], [], []
    for f in frames:
        gt = f.gt.boxes[class_mask(f.gt.boxes.label, gt_classes)]
        if not len(gt):
            continue
        dt = f.dt.boxes if f.kinds is None else f.dt.boxes[np.asarray(f.kinds) == "true"]
        returns.append(np.array([len(i) for i in points_in_boxes(f.points, gt, ground_margin=BODY_MARGIN)]))
        ranges.append(np.linalg.norm(gt.center[:, :2], axis=1))
        detected.append(iou_bev(gt, dt).max(axis=1) >= true_iou if len(dt) else np.zeros(len(gt), bool))
    if not returns:
        return {"returns": np.zeros(0, int), "range": np.zeros(0), "detected": np.zeros(0, bool)}
    return {"returns": np.concatenate(returns), "range": np.concatenate(ranges), "detected": np.concatenate(detected)}


def _bins(edges: tuple[float, ...], values: np.ndarray, integer: bool = False) -> list[tuple[str, np.ndarray]]:
    """(label, mask) per bin of ``edges`` (lower edges, the last bin open): ``1-4`` for integer
    counts, ``20-40`` for ranges."""
    out = []
    for i, lo in enumerate(edges):
        hi = edges[i + 1] if i + 1 < len(edges) else np.inf
        top = hi - 1 if integer else hi
        label = f"{lo:g}+" if hi == np.inf else f"{lo:g}" if top == lo else f"{lo:g}-{top:g}"
        out.append((label, (values >= lo) & (values < hi)))
    return out


def recall_table(rows: dict[str, np.ndarray]) -> dict[str, Any]:
    """Recall by returns and by range, and the true detections' sparse shares by range."""
    n, r, det = rows["returns"], rows["range"], rows["detected"]

    def recall(sel: np.ndarray) -> dict[str, Any]:
        return {"labelled": int(sel.sum()), "detected": int(det[sel].sum()),
                "recall": float(det[sel].mean()) if sel.any() else None}

    sparse = {}
    for label, sel in [*_bins(RANGE_BINS, r), ("all", np.ones(len(r), bool))]:
        hit = sel & det
        sparse[label] = {"true_detections": int(hit.sum()),
                         **{f"under_{c}": float((n[hit] < c).mean()) if hit.any() else None for c in SPARSE_CUTS}}
    return {"labelled": len(n), "detected": int(det.sum()),
            "recall_by_returns": {label: recall(sel) for label, sel in _bins(RETURN_BINS, n, integer=True)},
            "recall_by_range": {label: recall(sel) for label, sel in _bins(RANGE_BINS, r)},
            "true_detections_by_range": sparse}


def plot(tables: dict[str, dict[str, Any]], path: Path) -> None:
    """Recall by returns and by range, one line per source (bins without labelled cars left out,
    bins of fewer than :data:`FEW` cars hollow)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(12, 4.2))
    for name, t in tables.items():
        for a, key in zip(ax, ("recall_by_returns", "recall_by_range")):
            labels = list(t[key])
            xs = [i for i, b in enumerate(labels) if t[key][b]["labelled"]]
            line, = a.plot(xs, [t[key][labels[i]]["recall"] for i in xs], "-", label=f"{name} ({t['labelled']} cars)")
            for i in xs:  # hollow: a bin of fewer than FEW cars, a recall that says little
                colour = line.get_color()
                fill = "none" if t[key][labels[i]]["labelled"] < FEW else colour
                a.plot(i, t[key][labels[i]]["recall"], "o", color=colour, mfc=fill)
            a.set_xticks(range(len(labels)), labels)
    ax[0].set_xlabel("returns on the labelled car (more than 0.15 m above its bottom)")
    ax[1].set_xlabel("range, m")
    for a in ax:
        a.set_ylabel("recall (BEV IoU >= 0.3)")
        a.set_ylim(-0.02, 1.02)
        a.grid(alpha=0.3)
    ax[0].legend(fontsize=7)
    fig.suptitle("detector recall against returns: real detector vs the simulated one")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _frames(root: Path, detections: Path | None) -> list[LabelledFrame]:
    """Every sequence of a tracking root (or the object split)."""
    velodyne = root / "training" / "velodyne" if (root / "training").is_dir() else root / "velodyne"
    sequences = sorted(p.name for p in velodyne.iterdir() if p.is_dir()) or [None]
    det = detections if detections is not None else root / "detections" / "synthetic"
    return [f for s in sequences for f in load_kitti(root, det, s)]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m pcc_ros.workflows.detector_recall",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--kitti", type=Path, nargs="+", required=True,
                        help="KITTI-layout roots (real, or SynthCars with .kind files)")
    parser.add_argument("--detections", type=Path, nargs="*", default=[],
                        help="each root's detections directory (default ROOT/detections/synthetic); '-' = default")
    parser.add_argument("--gt-classes", default="Car,Van", help="labels counted as cars (Car,Van)")
    parser.add_argument("--true-iou", type=float, default=0.3, help="BEV IoU that makes a detection the car's (0.3)")
    parser.add_argument("--json", type=Path, help="write the tables here")
    parser.add_argument("--plot", type=Path, help="PNG of recall against returns and range")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    classes = tuple(c.strip() for c in args.gt_classes.split(",") if c.strip())
    dets = [None if d == Path("-") else d for d in args.detections] + [None] * len(args.kitti)
    tables = {}
    for root, det in zip(args.kitti, dets):
        t = recall_table(car_rows(_frames(root, det), classes, args.true_iou))
        tables[str(root)] = t
        print(f"{root}: {t['labelled']} labelled cars, {t['detected']} detected")
        print("  recall by returns: " + ", ".join(
            f"{b} {v['detected']}/{v['labelled']}" for b, v in t["recall_by_returns"].items() if v["labelled"]))
        print("  recall by range:   " + ", ".join(
            f"{b} m {v['detected']}/{v['labelled']}" for b, v in t["recall_by_range"].items() if v["labelled"]))
        print("  true detections with < 5 / 10 / 20 returns: " + ", ".join(
            f"{b} m ({v['true_detections']}) " + " / ".join(f"{v[f'under_{c}']:.0%}" for c in SPARSE_CUTS)
            for b, v in t["true_detections_by_range"].items() if v["true_detections"]))
    if args.json:
        write_json(args.json, tables, indent=1, nonfinite_null=True)
        log.info("wrote %s", args.json)
    if args.plot:
        plot(tables, args.plot)
        log.info("wrote %s", args.plot)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
