"""An hour of 10 Hz through the filter node's core: does its memory grow? (not in CI)

The shipped filter node's core (``NodeCore``, ``config/detection_filter.yaml``, ``device`` cpu,
the live node's worker thread and newest-wins hand-off) on the in-process graph, fed at
``--rate`` Hz for ``--minutes`` (default 60; ``make bench`` runs 5): scans of a SynthCars frame
(``--points``, default 120k) with a varying number of car boxes (0 to 40) whose track ids are new
in every frame, a share of pedestrians and of class ids no one configured, the detections in a
moving ``odom`` frame with ``/tf`` on the graph (the node's own ``/tf`` listener and its
``tf_timeout`` hold), and now and then a frame whose transform never comes (dropped, counted).
What could grow over a day: caches, per-track or per-class state, the tf buffer, numba / torch
allocators, queues.

The process's resident memory (``/proc/self/status``) is sampled every ``--sample-s`` seconds
(default: each minute, or 30 samples over a shorter run). Pass: after the warm-up (the first
``max(1 min, 10 %)`` of the run) the least-squares trend of the samples is at most
``--bound`` MB per hour (default 32: 5 % of the node's ~600 MB), *or* the peaks do not rise:
the highest sample of the second half after warm-up is at most 4 MB above the highest of the
first half (the allocators' dips of a few MB are memory given back; a leak lifts the peaks).
Over an hour of one sample a minute the trend resolves a few MB per hour; over 5 minutes the
samples' scatter (a few MB) makes its error about as large as the bound, and only the peaks
tell: they catch a leak of more than about 100 MB per hour. The RSS curve goes to ``--png``
(default ``benchmarks/results/soak.png``).
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np

from benchmarks.common import load_average
from benchmarks.scale import rss_mb

#: Memory within this many MB of its first post-warm-up value is flat, whatever its fitted trend.
FLAT_MB = 4.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--minutes", type=float, default=60.0, help="length of the run (default 60)")
    parser.add_argument("--rate", type=float, default=10.0, help="frames per second (default 10)")
    parser.add_argument("--points", type=int, default=120_000, help="points per scan (default 120000)")
    parser.add_argument("--sample-s", type=float, default=None,
                        help="seconds between RSS samples (default: 60, or the run / 30 when shorter)")
    parser.add_argument("--bound", type=float, default=32.0, help="MB per hour of trend after warm-up (default 32)")
    parser.add_argument("--png", type=Path, default=Path("benchmarks/results/soak.png"), help="the RSS curve")


def _frames(base, points: int, seed: int, pool: int = 24):
    """``pool`` scans (rosbags messages) of the base scan resized, and car / other boxes per frame."""
    from benchmarks.pipeline import car_boxes, resize_scan
    from benchmarks.scale import other_boxes
    from pcc_ros.msg.pointcloud2 import create_cloud
    from pcc_ros.types import Boxes

    scan, fields, vehicles, frame_id, stamp = base
    rng = np.random.default_rng(seed)
    out = []
    for k in range(pool):
        resized = resize_scan(scan, points, rng)
        cars = int(rng.integers(0, 41))
        boxes = car_boxes(resized, vehicles, cars, rng) if cars else None
        others = other_boxes(resized, int(rng.integers(0, 11)), rng)
        others = Boxes(others.center, others.size, others.yaw,
                       label=np.array([f"{lbl}" if k % 3 else str(rng.integers(3, 1000)) for lbl in others.label],
                                      dtype=object), score=others.score)  # now and then an id no one configured
        boxes = others if boxes is None else Boxes.concatenate([boxes, others])
        out.append((create_cloud(resized, fields, frame_id, stamp), boxes))
    return out


def _odom_from_velodyne(stamp_ns: int):
    from pcc_ros.geometry.rotations import quaternion_from_yaw
    from pcc_ros.geometry.transforms import Transform

    t = stamp_ns * 1e-9
    return Transform((5.0 * np.cos(0.01 * t), 5.0 * np.sin(0.01 * t), 1.7),
                     tuple(quaternion_from_yaw(0.01 * t).tolist()))


def verdict(times_s: np.ndarray, rss: np.ndarray, warmup_s: float, bound: float) -> dict:
    """Trend (MB / hour, least squares) and growth of the samples after ``warmup_s``; pass or not."""
    after = times_s >= warmup_s
    t, m = times_s[after], rss[after]
    slope = float(np.polyfit(t / 3600.0, m, 1)[0]) if len(t) >= 3 else float("nan")
    growth = float(m[-1] - m[0]) if len(m) else float("nan")
    half = len(m) // 2
    # the upper envelope: the allocators' dips are memory given back; a leak lifts the peaks
    envelope = float(m[half:].max() - m[:half].max()) if half else float("nan")
    flat = bool(half and envelope <= FLAT_MB)
    passed = bool(len(t) >= 3 and (slope <= bound or flat))
    return {"trend_mb_per_hour": slope, "growth_after_warmup_mb": growth, "envelope_growth_mb": envelope,
            "flat_within_mb": FLAT_MB, "flat": flat, "bound_mb_per_hour": bound,
            "samples_after_warmup": int(after.sum()), "passed": passed}


def plot(path: Path, times_s: np.ndarray, rss: np.ndarray, warmup_s: float, result: dict, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4))
    minutes = times_s / 60.0
    ax.axvspan(0, warmup_s / 60.0, color="0.9", label="warm-up")
    ax.plot(minutes, rss, "o-", ms=3, label="resident memory")
    after = times_s >= warmup_s
    if after.sum() >= 3:
        coef = np.polyfit(times_s[after] / 3600.0, rss[after], 1)
        ax.plot(minutes[after], np.polyval(coef, times_s[after] / 3600.0), "--",
                label=f"trend {result['trend_mb_per_hour']:+.1f} MB/h (bound {result['bound_mb_per_hour']:g})")
    ax.set_xlabel("minutes")
    ax.set_ylabel("RSS (MB)")
    ax.set_title(title, fontsize=9)
    ax.legend(loc="lower right", fontsize=8)
    ax.grid(alpha=0.3)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run(args: argparse.Namespace) -> dict:
    from tqdm import tqdm

    from benchmarks.pipeline import base_frame
    from pcc_ros.data.bag_writer import tf_message
    from pcc_ros.geometry.transforms import transform_boxes
    from pcc_ros.msg.detections import detection_array_from_boxes
    from pcc_ros.msg.stamps import make_header
    from pcc_ros.pipeline.config import load_parameters
    from pcc_ros.runtime.base import RELIABLE, SENSOR_DATA
    from pcc_ros.runtime.local import LocalGraph, LocalRuntime
    from pcc_ros.runtime.node import NodeCore
    from pcc_ros.runtime.tf import TF_MESSAGE, TF_QOS, TransformListener

    duration_s = args.minutes * 60.0
    sample_s = args.sample_s or min(60.0, duration_s / 30.0)
    warmup_s = max(60.0, 0.1 * duration_s)
    load_before = load_average()
    pool = _frames(base_frame(args.seed), args.points, args.seed)
    graph = LocalGraph()
    runtime = LocalRuntime(graph, "detection_filter_node")
    listener = TransformListener(runtime)
    runtime.lookup_transform = listener.lookup  # the wheels' path: the node's own /tf listener
    runtime.reset_transforms = listener.clear
    core = NodeCore(runtime, "detection_filter_node", "filter", load_parameters(None, True, device="cpu"))
    driver = LocalRuntime(graph, "driver")
    pub_cloud = driver.create_publisher("/points", "sensor_msgs/msg/PointCloud2", SENSOR_DATA)
    pub_dets = driver.create_publisher("/detections", "vision_msgs/msg/Detection3DArray", RELIABLE)
    pub_tf = driver.create_publisher("/tf", TF_MESSAGE, TF_QOS)
    period = 1.0 / args.rate
    samples: list[dict] = []
    start = time.monotonic()
    next_sample, frame = start, 0
    bar = tqdm(total=int(duration_s), unit="s", desc="soak", mininterval=5.0)
    try:
        while (now := time.monotonic()) - start < duration_s:
            if now >= next_sample:
                samples.append({"t_s": now - start, "rss_mb": rss_mb(), "frames": core.frames,
                                "dropped_newest_wins": core.pairer.stats.dropped_pairs,
                                "frames_without_transform": core.no_transform,
                                "latency_p50_ms": float(core.diagnostics_values()["latency_p50_ms"])})
                next_sample += sample_s
                bar.update(int(now - start) - bar.n)
            stamp = time.time_ns()
            cloud, boxes = pool[frame % len(pool)]
            cloud.header = make_header(cloud.header.frame_id, stamp)
            pose = _odom_from_velodyne(stamp)
            for dt in (-period / 2, period / 2):
                at = stamp + int(dt * 1e9)
                pub_tf.publish(tf_message([("odom", cloud.header.frame_id, _odom_from_velodyne(at).matrix())], at))
            lost = frame % 97 == 0  # now and then detections in a frame whose transform never comes
            dets = detection_array_from_boxes(transform_boxes(boxes, pose.matrix()), "map" if lost else "odom", stamp)
            for k, det in enumerate(dets.detections):
                det.id = f"{frame}-{k}"  # new track ids in every frame
            pub_cloud.publish(cloud)
            pub_dets.publish(dets)
            frame += 1
            time.sleep(max(0.0, start + frame * period - time.monotonic()))
        samples.append({"t_s": time.monotonic() - start, "rss_mb": rss_mb(), "frames": core.frames,
                        "dropped_newest_wins": core.pairer.stats.dropped_pairs,
                        "frames_without_transform": core.no_transform,
                        "latency_p50_ms": float(core.diagnostics_values()["latency_p50_ms"])})
    finally:
        bar.close()
        core.shutdown()
        runtime.shutdown()
    times = np.array([s["t_s"] for s in samples])
    rss = np.array([s["rss_mb"] for s in samples])
    result = verdict(times, rss, warmup_s, args.bound)
    values = core.diagnostics_values()
    title = (f"pcc bench soak --minutes {args.minutes:g}: filter node core at {args.rate:g} Hz, {args.points // 1000}k "
             f"points, 0-40 cars; {'PASS' if result['passed'] else 'FAIL'}")
    plot(args.png, times, rss, warmup_s, result, title)
    print(f"{frame} frames sent, {core.frames} answered, {values['dropped_pairs_newest_wins']} dropped (newest "
          f"wins), {core.no_transform} without transform; RSS {rss[0]:.0f} -> {rss[-1]:.0f} MB; after warm-up "
          f"({warmup_s / 60:.1f} min) trend {result['trend_mb_per_hour']:+.1f} MB/h (bound {args.bound:g}), growth "
          f"{result['growth_after_warmup_mb']:+.1f} MB, peaks {result['envelope_growth_mb']:+.1f} MB (second half vs "
          f"first): {'PASS' if result['passed'] else 'FAIL'}; curve: {args.png}")
    return {**result, "minutes": args.minutes, "rate_hz": args.rate, "points": args.points, "frames_sent": frame,
            "sample_s": sample_s, "warmup_s": warmup_s, "samples": samples, "diagnostics": values,
            "png": str(args.png), "cpu_count": os.cpu_count(), "load_average_before": load_before,
            "load_average_after": load_average()}
