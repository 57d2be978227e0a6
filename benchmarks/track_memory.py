"""Cost of track-level completion (``track_memory``): the pipeline per frame on a real KITTI
tracking sequence, each car completed from this frame's crop alone vs from its accumulated crops.

The labelled Car / Van boxes of ``../shared/data/kitti_tracking`` are the detections (their
track ids as ``Detection3D.id``; ``--no-ids`` leaves them empty, so the memory associates by
the nearest box). Each pass plays the 20 frames in order through two pipelines, one per
setting, interleaved frame by frame on the same frames; the first pass warms up, the next
``--repeat`` are timed. Reported: median ms per frame of the whole ``Pipeline.process``, of its
completion stage (the memory included) and of the memory's bookkeeping.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from benchmarks.common import load_average, print_table
from pcc_ros.paths import shared_data_dir

DEFAULT_DATA = shared_data_dir() / "kitti_tracking"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="KITTI tracking root (../shared/data/...)")
    parser.add_argument("--backend", default="pointpncnet", help="completion backend (default pointpncnet)")
    parser.add_argument("--repeat", type=int, default=5, help="timed passes over the sequence (default 5)")
    parser.add_argument("--no-ids", action="store_true", help="detections without ids: nearest-box association")


def run(args: argparse.Namespace) -> dict:
    from pcc_ros.data.sources import open_frames
    from pcc_ros.pipeline.core import Pipeline, PipelineConfig
    from pcc_ros.types import class_mask

    frames = []
    for frame in open_frames(args.data):  # 20 frames: the scans and their labelled vehicles
        boxes = frame.ground_truth[class_mask(frame.ground_truth.label, ("Car", "Van"))]
        if args.no_ids:
            boxes = replace(boxes, track_id=np.full(len(boxes), "", dtype=object))
        frames.append((np.asarray(frame.points)[:, :3].astype(np.float32), boxes, int(frame.index) * 100_000_000))
    base = PipelineConfig(backend=args.backend, workers=1)
    pipelines = {"single frame": Pipeline(base), "track memory": Pipeline(replace(base, track_memory=True))}
    samples: dict[str, dict[str, list[float]]] = {k: {"frame": [], "complete": [], "memory": []}
                                                 for k in pipelines}
    load_before = load_average()
    for rep in range(args.repeat + 1):
        for pipeline in pipelines.values():
            if pipeline.track_memory is not None:
                pipeline.track_memory.clear()
        for points, boxes, stamp in frames:
            for name, pipeline in pipelines.items():
                tic = time.perf_counter()
                result = pipeline.process(points, boxes, stamp)
                seconds = time.perf_counter() - tic
                if rep == 0:
                    continue
                s = samples[name]
                s["frame"].append(1e3 * seconds)
                s["complete"].append(result.timings_ms["complete_ms"])
                s["memory"].append(result.timings_ms.get("track_memory_ms", 0.0))
    rows, out = [], {}
    for name, s in samples.items():
        row = {"setting": name, "frame ms (median)": float(np.median(s["frame"])),
               "complete ms (memory included)": float(np.median(s["complete"])),
               "memory ms": float(np.median(s["memory"]))}
        rows.append(row)
        out[name] = row
    print_table(f"track memory, {args.backend}, {len(frames)} frames x {args.repeat} passes "
                f"({'nearest-box association' if args.no_ids else 'ids'})", rows)
    out["load_average"] = {"before": load_before, "after": load_average()}
    return out
