"""A hostile frame through the pipeline: hundreds of huge boxes over a real 120k-point scan.

The frame the reliability issue (#20) measured at 8.8 s and 1.1 GB: ``--boxes`` detections
of ``--size`` metres (within ``max_box_size``, so only the work bound can help) scattered
around the sensor of KITTI tracking 0000 frame 0, through :meth:`Pipeline.process_messages`
with the shipped ``detection_filter.yaml`` (PointPnCNet). Compared in the same process: the
default ``max_crop_work`` against the bound switched off (``max_crop_work`` = 10^15). Wall
time of each (median of ``--repeat`` calls for the bounded one, one call unbounded) and the
peak of numpy / Python allocations during one call (tracemalloc, a separate call).
"""

from __future__ import annotations

import argparse
import time
import tracemalloc
from pathlib import Path

import numpy as np

from benchmarks.common import load_average, print_table
from pcc_ros.paths import shared_data_dir

DEFAULT_DATA = shared_data_dir() / "kitti_tracking"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="KITTI tracking root (../shared/data/...)")
    parser.add_argument("--boxes", type=int, default=200, help="detections in the frame (default 200)")
    parser.add_argument("--size", type=float, default=30.0, help="box length = width, metres (default 30)")
    parser.add_argument("--repeat", type=int, default=3, help="timed calls of the bounded pipeline")


def _frame(data: Path, boxes: int, size: float, seed: int):
    from pcc_ros.data.kitti import KittiTracking
    from pcc_ros.msg.detections import detection_array_from_boxes
    from pcc_ros.msg.pointcloud2 import create_cloud
    from pcc_ros.types import Boxes

    frame = next(KittiTracking(data).frames("0000", stop=1))
    rng = np.random.default_rng(seed)
    hostile = Boxes(np.c_[rng.uniform(-10, 10, (boxes, 2)), np.full(boxes, -0.5)],
                    np.c_[np.full((boxes, 2), size), np.full(boxes, 4.0)], rng.uniform(-np.pi, np.pi, boxes),
                    np.array(["Car"] * boxes, dtype=object), rng.uniform(0, 1, boxes),
                    np.array([str(i) for i in range(boxes)], dtype=object))
    cloud = create_cloud(frame.points, list(frame.fields), "velodyne", frame.stamp_ns)
    return cloud, detection_array_from_boxes(hostile, "velodyne", frame.stamp_ns), len(frame.points)


def _peak_mb(fn) -> float:
    tracemalloc.start()
    try:
        fn()
        return tracemalloc.get_traced_memory()[1] / 1e6
    finally:
        tracemalloc.stop()


def run(args: argparse.Namespace) -> dict:
    import dataclasses

    from pcc_ros.pipeline.config import load_config
    from pcc_ros.pipeline.core import Pipeline

    cloud, dets, n_points = _frame(args.data, args.boxes, args.size, args.seed)
    config, _ = load_config(None, with_filter=True)
    bounded = Pipeline(config)
    unbounded = Pipeline(dataclasses.replace(config, max_crop_work=10**15), completer=bounded.completer)
    bounded.process_messages(cloud, dets)  # warm-up (lazy imports, first torch call)
    rows, results = [], {"points": n_points, "boxes": args.boxes, "size_m": args.size, "load_before": load_average()}
    for name, pipe, repeat in (("max_crop_work default", bounded, args.repeat), ("unbounded", unbounded, 1)):
        seconds = []
        for _ in range(repeat):
            tic = time.perf_counter()
            result, _ = pipe.process_messages(cloud, dets)
            seconds.append(time.perf_counter() - tic)
        peak = _peak_mb(lambda p=pipe: p.process_messages(cloud, dets))
        judged = int(np.isin(result.status, ("kept", "rejected")).sum())
        row = {"pipeline": name, "s_per_frame": float(np.median(seconds)), "peak_alloc_mb": peak,
               "boxes_judged": judged, "boxes_completed": len(result.completed_index),
               "boxes_unjudged": int((result.status == "unjudged").sum()), "skipped": dict(result.skipped)}
        rows.append({k: v for k, v in row.items() if k != "skipped"})
        results[name] = row
    results["load_after"] = load_average()
    print_table(f"hostile frame: {args.boxes} boxes of {args.size:g} m over {n_points} points "
                f"(load {results['load_before'][0]:.1f})", rows)
    return results
