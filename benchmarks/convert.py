"""Bag write / read throughput on full 120k-point scans (MCAP + zstd levels, sqlite3).

Frames are real KITTI tracking scans with their labels and PointRCNN detections when
``../shared/data/kitti_tracking`` (or ``--kitti``) exists, else seeded random scans of
``--points`` points with random boxes. They are loaded into memory first, so the write
rate is the bag writer's own (PointCloud2 + Detection3DArray + CDR + compression + disk)
and the read rate is :func:`pcc_ros.data.bag.read_frames` decoding complete frames.
Each configuration is timed ``--repeat`` times; the median is reported, with ratios
against uncompressed MCAP measured in the same process. The headline
``write_frames_per_s`` / ``read_frames_per_s`` are the default configuration
(MCAP, zstd level 3).
"""

from __future__ import annotations

import argparse
import logging
import shutil
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from benchmarks.common import print_table
from pcc_ros.data.bag import read_frames
from pcc_ros.data.bag_writer import write_bag
from pcc_ros.paths import shared_data_dir
from pcc_ros.types import Boxes, Sample

_DEFAULT_KITTI = shared_data_dir() / "kitti_tracking"
# (name, storage, compress, zstd level)
CONFIGS = [
    ("mcap none", "mcap", False, None),
    ("mcap zstd-1", "mcap", True, 1),
    ("mcap zstd-3 (default)", "mcap", True, None),
    ("sqlite3 none", "sqlite3", False, None),
    ("sqlite3 msg zstd", "sqlite3", True, None),
]
DEFAULT = "mcap zstd-3 (default)"


#: Frames per second of the default configuration that the conversion must reach (2 cores).
TARGETS = {"write_frames_per_s": 20.0, "read_frames_per_s": 100.0}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--frames", type=int, default=40, help="frames per bag (default 40)")
    parser.add_argument("--repeat", type=int, default=3, help="timed runs per configuration (median)")
    parser.add_argument("--points", type=int, default=120_000, help="points per random scan (no KITTI data)")
    parser.add_argument("--kitti", type=Path, default=_DEFAULT_KITTI, help="KITTI tracking root for real scans")
    parser.add_argument("--tmp", type=Path, default=None, help="directory for the bags (default: system temp)")


def _frames(args: argparse.Namespace) -> tuple[list[Sample], str]:
    n = args.frames
    if args.kitti and (args.kitti / "training" / "velodyne" / "0000").is_dir():
        from pcc_ros.data.kitti import KittiTracking

        dets = args.kitti / "detections" / "pointrcnn"
        base = list(KittiTracking(args.kitti).frames("0000", dets if dets.is_dir() else None))
        frames = [
            replace(base[i % len(base)], stamp_ns=base[0].stamp_ns + i * 100_000_000, index=i) for i in range(n)
        ]
        return frames, f"KITTI tracking 0000 ({len(base)} scans cycled)"
    rng = np.random.default_rng(args.seed)
    frames = []
    for i in range(n):
        xyz = rng.normal(0.0, 15.0, size=(args.points, 3)).astype(np.float32)
        intensity = rng.random((args.points, 1), dtype=np.float32)
        boxes = Boxes(rng.uniform(-30, 30, (10, 3)), rng.uniform(1, 5, (10, 3)), rng.uniform(-3, 3, 10),
                      track_id=[str(k) for k in range(10)])
        frames.append(Sample(i * 100_000_000, "velodyne", np.hstack([xyz, intensity]), ground_truth=boxes,
                            detections=boxes, sequence="random", index=i))
    return frames, f"random scans, seed {args.seed}"


def _time_config(frames: list[Sample], tmp: Path, storage: str, compress: bool, level: int | None, repeat: int) -> dict:
    write_s, read_s, size = [], [], 0
    for k in range(repeat):
        out = tmp / f"bag_{storage}_{compress}_{level}_{k}"
        start = time.perf_counter()
        summary = write_bag(frames, out, storage=storage, compress=compress, zstd_level=level, progress=False)
        write_s.append(time.perf_counter() - start)
        size = summary.bytes
        start = time.perf_counter()
        count = sum(1 for _ in read_frames(out))
        read_s.append(time.perf_counter() - start)
        if count != len(frames):
            raise RuntimeError(f"read {count} frames back from {out}, wrote {len(frames)}")
        shutil.rmtree(out)
    n = len(frames)
    return {
        "write_frames_per_s": n / float(np.median(write_s)),
        "read_frames_per_s": n / float(np.median(read_s)),
        "mb_per_frame": size / n / 1e6,
    }


def run(args: argparse.Namespace) -> dict:
    frames, source = _frames(args)
    raw_mb = float(np.mean([f.points.nbytes for f in frames])) / 1e6
    tmp = Path(tempfile.mkdtemp(prefix="pcc_bench_convert_", dir=args.tmp))
    logging.getLogger("pcc_ros.data.bag_writer").setLevel(logging.WARNING)  # one DontCare note per run is noise here
    try:
        results = {name: _time_config(frames, tmp, *cfg, args.repeat) for name, *cfg in CONFIGS}
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    base = results["mcap none"]
    rows = [
        {
            "config": name,
            "write fr/s": r["write_frames_per_s"],
            "read fr/s": r["read_frames_per_s"],
            "MB/frame": r["mb_per_frame"],
            "write x": r["write_frames_per_s"] / base["write_frames_per_s"],
            "read x": r["read_frames_per_s"] / base["read_frames_per_s"],
            "size x": r["mb_per_frame"] / base["mb_per_frame"],
        }
        for name, r in results.items()
    ]
    print_table(
        f"bag conversion: {len(frames)} frames of {np.mean([len(f.points) for f in frames]):.0f} points "
        f"({raw_mb:.2f} MB raw), {source}; ratios vs. uncompressed MCAP",
        rows,
    )
    default = results[DEFAULT]
    print(f"\ndefault ({DEFAULT}): write {default['write_frames_per_s']:.1f} frames/s (target >= "
          f"{TARGETS['write_frames_per_s']:.0f}), read {default['read_frames_per_s']:.1f} frames/s (target >= "
          f"{TARGETS['read_frames_per_s']:.0f})")
    return {
        "targets": TARGETS,
        "targets_met": all(default[k] >= v for k, v in TARGETS.items()),
        "write_frames_per_s": default["write_frames_per_s"],
        "read_frames_per_s": default["read_frames_per_s"],
        "frames": len(frames),
        "points_per_frame": float(np.mean([len(f.points) for f in frames])),
        "source": source,
        "configs": results,
    }
