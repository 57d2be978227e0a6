"""Crop + canonicalise car boxes from a real 120k-point scan, against an open3d loop.

Ours: :func:`pcc_ros.geometry.boxes.crop_canonical` (one vectorised pass for all boxes).
Baseline, in the same process on the same boxes: the scan converted to open3d's
``Vector3dVector`` once (included in its time), then per box
``OrientedBoundingBox.get_point_indices_within_bounding_box`` and
:func:`pcc_ros.geometry.canonical.to_canonical` of the crop. Also the crop of 93cd59e
(``benchmarks/_reference.py``, before the #19 work). The three are timed call by call,
interleaved (min / median / max of ``--repeat`` calls each, after a warm-up), with the
machine's load average recorded; the point sets are compared first (open3d: the same
points per box; 93cd59e: the same indices and bit-identical canonical points). Box sets of 5, 30 and
100 boxes: the scan's labelled boxes first, then boxes of car size standing on the ground
under random above-ground returns (realistic crops, sometimes overlapping).
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import numpy as np

from benchmarks._reference import crop_canonical as reference_crop
from benchmarks.common import interleaved, load_average, print_table, summary_ms
from pcc_ros.data.kitti_format import Calibration, camera_to_lidar_boxes, parse_label_lines
from pcc_ros.errors import DataError
from pcc_ros.geometry.boxes import crop_canonical
from pcc_ros.geometry.canonical import to_canonical
from pcc_ros.paths import shared_data_dir
from pcc_ros.types import Boxes

DEFAULT_SCAN = shared_data_dir() / "kitti_tracking"
TARGET_SPEEDUP = 3.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", type=Path, default=DEFAULT_SCAN, help="KITTI tracking root (../shared/data/...)")
    parser.add_argument("--frame", type=int, default=0, help="frame of sequence 0000")
    parser.add_argument("--boxes", type=str, default="5,30,100", help="box counts to measure")
    parser.add_argument("--repeat", type=int, default=50, help="timed calls of each (interleaved)")
    parser.add_argument("--margin", type=float, default=0.1, help="box margin, metres")


def load_scan(root: Path, frame: int) -> tuple[np.ndarray, Boxes]:
    """One real scan of KITTI tracking sequence 0000 and its labelled boxes (LiDAR frame)."""
    bin_path = root / "training" / "velodyne" / "0000" / f"{frame:06d}.bin"
    if not bin_path.is_file():
        raise DataError(f"{bin_path}: scan not found (pass --data)")
    raw = np.fromfile(bin_path, dtype=np.float32)
    if raw.size % 4:
        raise DataError(f"{bin_path}: size is not a multiple of 4 floats")
    points = raw.reshape(-1, 4)
    calib = Calibration.read(root / "training" / "calib" / "0000.txt")
    label_path = root / "training" / "label_02" / "0000.txt"
    rows = parse_label_lines(label_path.read_text().splitlines(), tracking=True, source=str(label_path))
    rows = rows[(rows.frame == frame) & (rows.type != "DontCare")]
    return points, camera_to_lidar_boxes(rows, calib)


def box_set(points: np.ndarray, labelled: Boxes, n: int, rng: np.random.Generator) -> Boxes:
    """``n`` boxes: the labelled ones, then car-sized boxes centred on random scan points."""
    take = labelled[: min(n, len(labelled))]
    extra = n - len(take)
    if extra <= 0:
        return take
    # Car-like boxes standing on the ground (KITTI's sensor is 1.73 m above it) under
    # random above-ground returns within 40 m, like a detector's boxes on real objects.
    dist = np.linalg.norm(points[:, :2], axis=1)
    near = points[(dist > 3.0) & (dist < 40.0) & (points[:, 2] > -1.2)]
    centres = near[rng.choice(len(near), extra, replace=False), :3].astype(np.float64)
    size = np.c_[rng.uniform(3.5, 5.0, extra), rng.uniform(1.5, 2.0, extra), rng.uniform(1.4, 1.8, extra)]
    centres[:, 2] = -1.73 + size[:, 2] / 2.0
    random = Boxes(centres, size, rng.uniform(-np.pi, np.pi, extra))
    return Boxes.concatenate([take, random])


def _open3d_boxes(boxes: Boxes) -> list:
    import open3d as o3d

    out = []
    for i in range(len(boxes)):  # the baseline is a per-box loop by definition
        c, s = np.cos(boxes.yaw[i]), np.sin(boxes.yaw[i])
        rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        out.append(o3d.geometry.OrientedBoundingBox(boxes.center[i], rot, boxes.size[i]))
    return out


def open3d_indices(points: np.ndarray, boxes: Boxes) -> list[np.ndarray]:
    """open3d's oriented-box index query per box."""
    import open3d as o3d

    cloud = o3d.utility.Vector3dVector(points[:, :3].astype(np.float64))
    return [np.asarray(b.get_point_indices_within_bounding_box(cloud), dtype=np.int64) for b in _open3d_boxes(boxes)]


def open3d_crop(points: np.ndarray, boxes: Boxes) -> list[np.ndarray]:
    """The baseline: open3d's oriented-box index query looped over boxes, then canonicalise."""
    out = []
    for i, idx in enumerate(open3d_indices(points, boxes)):
        out.append(to_canonical(points[idx], boxes.center[i], boxes.yaw[i], boxes.size[i, 0]).astype(np.float32))
    return out


def run(args: argparse.Namespace) -> dict:
    load_before = load_average()
    rng = np.random.default_rng(args.seed)
    points, labelled = load_scan(args.data, args.frame)
    rows, spread = [], {}
    for n in [int(v) for v in args.boxes.split(",")]:
        boxes = box_set(points, labelled, n, rng)
        # Agreement on the margin-free crops (open3d has no margin): the same points per box,
        # up to points within float rounding of a face (open3d tests in float64).
        ours_idx, _ = crop_canonical(points, boxes)
        theirs_idx = [np.sort(i) for i in open3d_indices(points, boxes)]
        differing = sum(len(np.setxor1d(a, b)) for a, b in zip(ours_idx, theirs_idx))
        # The 93cd59e crop: without a margin the same indices and canonical points, bit for bit;
        # with the margin it misses points near the enlarged corners of yawed boxes (the bug
        # fixed since): ours holds all of its points, and those (counted).
        ours_full = crop_canonical(points, boxes, ground_margin=0.1)
        ref_full = reference_crop(points, boxes, ground_margin=0.1)
        if not all(np.array_equal(a, b) for part in (0, 1) for a, b in zip(ours_full[part], ref_full[part])):
            raise SystemExit(f"{n} boxes: the crop differs from the 93cd59e crop")
        ours_m, ref_m = crop_canonical(points, boxes, args.margin)[0], reference_crop(points, boxes, args.margin)[0]
        if any(len(np.setdiff1d(b, a)) for a, b in zip(ours_m, ref_m)):
            raise SystemExit(f"{n} boxes: the crop misses points of the 93cd59e crop")
        ref_missed = sum(len(np.setdiff1d(a, b)) for a, b in zip(ours_m, ref_m))
        # Interleaved call by call on the same inputs (ours with the pipeline's margin).
        times = interleaved(
            {"ours": lambda b=boxes: crop_canonical(points, b, margin=args.margin),
             "open3d": lambda b=boxes: open3d_crop(points, b),
             "93cd59e": lambda b=boxes: reference_crop(points, b, margin=args.margin)},
            repeat=args.repeat, warmup=3,
        )
        ours, o3d, ref = summary_ms(times["ours"]), summary_ms(times["open3d"]), summary_ms(times["93cd59e"])
        spread[n] = {"ours": ours, "open3d": o3d, "93cd59e": ref}
        rows.append(
            {
                "boxes": n,
                "scan_points": len(points),
                "cropped_points": int(sum(len(i) for i in ours_idx)),
                "points_differing": int(differing),
                "93cd59e_missed": int(ref_missed),
                "ours_min": ours["min_ms"], "ours_ms": ours["median_ms"], "ours_max": ours["max_ms"],
                "open3d_min": o3d["min_ms"], "open3d_ms": o3d["median_ms"], "open3d_max": o3d["max_ms"],
                "speedup_vs_open3d": o3d["median_ms"] / ours["median_ms"],
                "93cd59e_ms": ref["median_ms"],
                "speedup_vs_93cd59e": ref["median_ms"] / ours["median_ms"],
            }
        )
    print_table(f"crop + canonicalise, ms ({args.repeat} interleaved calls each: min / median / max)", rows)
    at30 = next((r for r in rows if r["boxes"] == 30), None)
    result = {"rows": rows, "timings": spread, "scan": str(args.data), "frame": args.frame,
              "cpu_count": os.cpu_count(), "load_average_before": load_before, "load_average_after": load_average()}
    if at30:
        result.update({k: at30[k] for k in ("ours_ms", "open3d_ms", "speedup_vs_open3d")})
        result["target_met"] = bool(at30["speedup_vs_open3d"] >= TARGET_SPEEDUP)
        result["target_speedup"] = TARGET_SPEEDUP
        print(f"\n30 boxes: {at30['ours_ms']:.2f} ms vs open3d {at30['open3d_ms']:.2f} ms (medians, interleaved) "
              f"-> {at30['speedup_vs_open3d']:.2f}x (target >= {TARGET_SPEEDUP}x: "
              f"{'met' if result['target_met'] else 'NOT met'})")
    print(f"load average (1 min) before / after: {load_before[0]:.2f} / {result['load_average_after'][0]:.2f} "
          f"on {os.cpu_count()} cores")
    return result
