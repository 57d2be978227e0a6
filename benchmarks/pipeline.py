"""Per-frame latency of the whole pipeline, as a node runs it: fast vs original paths, scaling.

A full-resolution SynthCars frame (HDL-64E-like, ~110k points) resized to the requested point
count (a random subset, or jittered copies of the scan) with the requested number of car
detections (the frame's nearest vehicles, then car-sized boxes standing under random
above-ground returns) goes through ``Pipeline.process_messages`` + ``build_outputs`` (decode,
crop, canonicalise, complete, filter, encode of the completed cloud, markers and detection
arrays), frame after frame, in the message classes a node uses (rclpy's, when the ROS 2 wheels
are installed; rosbags' otherwise), every output built (a node with a viewer subscribed to its
markers; without one it skips them).

1. Headline, 20 cars / 120k points, three alternatives interleaved frame by frame in one
   process on the same messages, for each thread setting (torch intra-op threads, and
   ``WxN``: ``W`` completion workers with ``N`` intra-op threads each, the pipeline's
   ``workers`` parameter; the filter measures on as many threads as the completion has
   (``pipeline.core.filter_threads``), its ground and expected-returns terms on a second thread
   when that is 2 or more):

   * ``original`` -- today's pipeline: the network's original path
     (the completer's ``reference`` inference path) and the crop, work estimate and evidence
     measurements of main at 93cd59e (``benchmarks._reference.original_geometry``), computing
     what the shipped filter computes: the local ground over the beam model's reach
     (``pcc_ros.pipeline.evidence.ground_reach``, newer than 93cd59e's fixed 3 m) and the
     profile terms (the shipped pass on both sides: they have no 93cd59e counterpart), so the
     outputs compare bit for bit and the ratio times the algorithms, not different semantics;
   * ``orig_net`` -- the network's original path only, everything else fast (the
     conservative reference: the geometry gains count for both sides);
   * ``fast`` -- the pipeline as it ships.

   Outputs are checked equal first: same decisions, filter probabilities and terms
   (bit-identical), points per box, and completed clouds within 1e-4 m. The headline ratio
   is the fast pipeline at its best setting against today's at its best (any setting); the
   conservative ratio and the same-setting ratios are printed too.
2. Scaling (fast path, best thread setting): cars 1/5/20/50/100 at 120k points and points
   30k/120k/250k at 20 cars, with the stage breakdown (median ms per stage).

The machine's load average is recorded before and after (this machine is shared; an idle
2-core machine is the setting of the p95 target). Targets (issue #19): >= 1.8x today's
pipeline at 20 cars / 120k points; p95 <= 50 ms on an idle 2-core machine; the filter stage
<= 25 % of the completion stage at 20 cars.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import os
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from benchmarks.common import inference_path, load_average, print_table, summary_ms
from benchmarks.complete import parse_threads, thread_label

STAGES = ("decode_ms", "crop_ms", "complete_ms", "filter_ms", "uncanonical_ms", "encode_ms")
TARGET_SPEEDUP = 1.8
TARGET_P95_MS = 50.0
TARGET_FILTER_SHARE = 0.25
ALTERNATIVES = ("original", "orig_net", "fast")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--backend", default="pointpncnet", help="backend under test")
    parser.add_argument("--checkpoint", help="checkpoint (default: shipped weights; untrained if none)")
    parser.add_argument("--cars", type=int, default=20, help="car detections of the headline frame (default 20)")
    parser.add_argument("--points", type=int, default=120_000, help="points of the headline frame (default 120000)")
    parser.add_argument("--threads", default="1,2,2x1",
                        help="settings: N torch intra-op threads, or WxN = W completion workers x N (default 1,2,2x1)")
    parser.add_argument("--repeat", type=int, default=30, help="timed frames per alternative (default 30)")
    parser.add_argument("--scale-cars", default="1,5,20,50,100", help="car counts of the scaling table")
    parser.add_argument("--scale-points", default="30000,120000,250000", help="point counts of the scaling table")
    parser.add_argument("--scale-repeat", type=int, default=10,
                        help="timed frames per scaling row (default 10; 0: no scaling table)")


@contextlib.contextmanager
def original_paths(completer, geometry: bool = True) -> Iterator[None]:
    """Today's code paths, kept selectable for this comparison: the network's original path
    (``completer``'s ``reference`` inference path; a backend without one has no other) and
    (``geometry``) the crop, work estimate and evidence measurements of main at 93cd59e."""
    from benchmarks._reference import original_geometry

    network = inference_path(completer, "reference") if hasattr(completer, "inference_path") else \
        contextlib.nullcontext()
    with network, original_geometry() if geometry else contextlib.nullcontext():
        yield


def _paths(name: str, completer):
    """The context manager of one alternative of :data:`ALTERNATIVES`."""
    if name == "fast":
        return contextlib.nullcontext()
    return original_paths(completer, geometry=name == "original")


def base_frame(seed: int):
    """One full-resolution SynthCars frame: (points (N, C), fields, vehicles Boxes, frame_id, stamp)."""
    from pcc_ros.data.kitti import KittiTracking
    from pcc_ros.data.synthetic import generate

    with tempfile.TemporaryDirectory() as tmp:
        generate(tmp, sequences=1, frames=1, seed=seed, progress=False)
        frame = next(KittiTracking(Path(tmp) / "training").frames("0000"))
    gt = frame.ground_truth
    vehicles = gt[np.array([str(lbl) in ("Car", "Van") for lbl in gt.label]) & gt.valid_mask()]
    order = np.argsort(np.linalg.norm(vehicles.center[:, :2], axis=1), kind="stable")  # nearest first
    return np.asarray(frame.points), tuple(frame.fields), vehicles[order], frame.frame_id, frame.stamp_ns


def resize_scan(points: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` rows: a random subset in scan order, or the scan plus jittered copies (denser sensor)."""
    if n <= len(points):
        return points[np.sort(rng.choice(len(points), n, replace=False))]
    extra = points[rng.integers(0, len(points), n - len(points))].copy()
    extra[:, :3] += rng.normal(0.0, 0.02, (len(extra), 3)).astype(points.dtype)
    return np.concatenate([points, extra])


def car_boxes(points: np.ndarray, vehicles, n: int, rng: np.random.Generator):
    """``n`` detections: the nearest labelled vehicles, then car-sized boxes on random returns."""
    from pcc_ros.types import Boxes

    take = vehicles[np.arange(min(n, len(vehicles)))]
    extra = n - len(take)
    if extra <= 0:
        return take
    xyz = points[:, :3].astype(np.float64)
    dist = np.linalg.norm(xyz[:, :2], axis=1)
    near = xyz[(dist > 3.0) & (dist < 40.0) & (xyz[:, 2] > -1.2)]
    centres = near[rng.choice(len(near), extra, replace=len(near) < extra)]
    size = np.c_[rng.uniform(3.5, 5.0, extra), rng.uniform(1.5, 2.0, extra), rng.uniform(1.4, 1.8, extra)]
    centres[:, 2] = -1.73 + size[:, 2] / 2.0
    boxes = Boxes(centres, size, rng.uniform(-np.pi, np.pi, extra), label=np.array(["Car"] * extra, dtype=object),
                  score=rng.uniform(0.3, 0.9, extra))
    return Boxes.concatenate([take, boxes])


def node_classes():
    """The message classes a node publishes and receives: rclpy's when it imports (the ROS 2
    wheels of ``make setup``), else rosbags' (``pcc replay``'s). rclpy's constructors build
    every default sub-message eagerly, so the encode stage costs about 2.5x as much with them."""
    try:
        from pcc_ros.nodes.ros_node import rclpy_classes
    except ImportError:
        return None
    return rclpy_classes


def frame_messages(base, cars: int, points: int, seed: int, classes=None):
    """(PointCloud2, Detection3DArray, n_cars, n_points) for one benchmark frame (messages of
    ``classes``, None: rosbags)."""
    from pcc_ros.msg.detections import detection_array_from_boxes
    from pcc_ros.msg.pointcloud2 import create_cloud

    scan, fields, vehicles, frame_id, stamp = base
    rng = np.random.default_rng(seed)
    scan = resize_scan(scan, points, rng)
    dets = car_boxes(scan, vehicles, cars, rng)
    cloud = create_cloud(scan, fields, frame_id, stamp, classes)
    return cloud, detection_array_from_boxes(dets, frame_id, stamp, classes), len(dets), len(scan)


def one_frame(pipeline, cloud, dets, classes=None) -> tuple[dict[str, float], object]:
    """Run one frame as a node does, every output built (a node with a viewer subscribed) in the
    message ``classes`` of the received ones (:func:`node_classes`); per-stage and total ms."""
    from pcc_ros.pipeline.outputs import build_outputs

    tic = time.perf_counter()
    result, originals = pipeline.process_messages(cloud, dets)
    enc = time.perf_counter()
    outputs = build_outputs(result, originals, classes)
    done = time.perf_counter()
    stages = {s: result.timings_ms.get(s, 0.0) for s in STAGES[:-1]}
    stages["encode_ms"] = (done - enc) * 1e3
    stages["total_ms"] = (done - tic) * 1e3
    return stages, (result, outputs)


def make_pipeline(backend: str, checkpoint: str | None):
    from pcc_ros.models.registry import create, default_checkpoint, get_backend, load_completer
    from pcc_ros.pipeline.core import Pipeline, PipelineConfig

    config = PipelineConfig(backend=backend, device="cpu", min_points=5, max_instances=128)
    cls = get_backend(backend)
    trained = not cls.learned or checkpoint or default_checkpoint(backend)
    completer = load_completer(backend, checkpoint, device="cpu") if trained else create(backend, device="cpu")
    return Pipeline(config, completer=completer), bool(trained)


def check_equal(a, b) -> float:
    """Same decisions, filter probabilities and terms, points per box and completed clouds
    (max |diff| returned); raises SystemExit otherwise."""
    ra, rb = a[0], b[0]
    if not np.array_equal(ra.status, rb.status):
        raise SystemExit(f"fast and original pipelines disagree on decisions: {ra.status} vs {rb.status}")
    if not np.array_equal(ra.num_points, rb.num_points):
        raise SystemExit(f"fast and original crops differ: {ra.num_points} vs {rb.num_points} points per box")
    scores = [(ra.filter_score, rb.filter_score)]
    scores += [(ra.filter_terms[k], rb.filter_terms.get(k)) for k in ra.filter_terms]
    if set(ra.filter_terms) != set(rb.filter_terms) or not all(
        (x is None and y is None) or (x is not None and y is not None and np.array_equal(x, y, equal_nan=True))
        for x, y in scores
    ):
        bad = [k for k in ra.filter_terms
               if not np.array_equal(ra.filter_terms[k], rb.filter_terms.get(k), equal_nan=True)]
        raise SystemExit(f"fast and original filters give different probabilities or terms: {bad}")
    if ra.completed_points.shape != rb.completed_points.shape or not np.array_equal(
        ra.completed_instance, rb.completed_instance
    ):
        raise SystemExit("fast and original pipelines produce differently shaped completed clouds")
    diff = float(np.abs(ra.completed_points - rb.completed_points).max()) if len(ra.completed_points) else 0.0
    if diff > 1e-4:
        raise SystemExit(f"fast and original completed clouds differ by {diff:.2e} m")
    if set(a[1]) != set(b[1]):
        raise SystemExit("fast and original pipelines publish different topics")
    return diff


def stage_rows(samples: list[dict[str, float]]) -> dict[str, float]:
    return {s: float(np.median([x[s] for x in samples])) for s in (*STAGES, "total_ms")}


def run(args: argparse.Namespace) -> dict:
    import torch

    load_before = load_average()
    base = base_frame(args.seed)
    pipeline, trained = make_pipeline(args.backend, args.checkpoint)
    classes = node_classes()
    cloud, dets, n_cars, n_points = frame_messages(base, args.cars, args.points, args.seed, classes)
    from pcc_ros.runtime.heap import freeze_long_lived

    freeze_long_lived()  # as a node does once it has started (NodeCore): its message classes loaded too
    weights = "trained" if trained else "untrained (same cost)"

    # ---- 1. headline: original vs fast, interleaved frame by frame, per thread setting
    torch.set_num_threads(1)
    outs = {}
    for name in ALTERNATIVES:
        with _paths(name, pipeline.completer):
            outs[name] = one_frame(pipeline, cloud, dets, classes)[1]
    max_diff = max(check_equal(outs["fast"], outs[name]) for name in ALTERNATIVES[:-1])
    rows, headline = [], {}
    settings = parse_threads(args.threads)
    for setting in settings:
        workers, threads = setting
        torch.set_num_threads(threads)
        if hasattr(pipeline.completer, "workers"):
            pipeline.completer.workers = workers
        pipeline.config = dataclasses.replace(pipeline.config, workers=workers)  # the filter's threads too
        samples: dict[str, list[dict[str, float]]] = {name: [] for name in ALTERNATIVES}
        for i in range(args.repeat + 3):  # 3 warm-up frames each
            for name in ALTERNATIVES if i % 2 == 0 else ALTERNATIVES[::-1]:
                with _paths(name, pipeline.completer):
                    stages = one_frame(pipeline, cloud, dets, classes)[0]
                if i >= 3:
                    samples[name].append(stages)
        summary = {name: summary_ms(np.array([s["total_ms"] for s in samples[name]]) / 1e3) for name in ALTERNATIVES}
        orig, net, fast = (summary[name] for name in ALTERNATIVES)
        row = {"threads": thread_label(setting), "original_p50": orig["median_ms"], "original_p95": orig["p95_ms"],
               "orig_net_p50": net["median_ms"],
               "fast_min": fast["min_ms"], "fast_p50": fast["median_ms"], "fast_p95": fast["p95_ms"],
               "fast_max": fast["max_ms"], "speedup_p50": orig["median_ms"] / fast["median_ms"],
               "speedup_vs_orig_net": net["median_ms"] / fast["median_ms"]}
        rows.append(row)
        headline[thread_label(setting)] = {**row, "original": orig, "orig_net": net, "fast": fast,
                                  **{f"{name}_stages_ms": stage_rows(samples[name]) for name in ALTERNATIVES}}
    print_table(f"whole frame, {n_points} points, {n_cars} cars ({weights} {args.backend}; "
                f"{'rclpy' if classes is not None else 'rosbags'} messages); ms, "
                f"{args.repeat} frames each, interleaved (original = today's pipeline at 93cd59e; orig_net = "
                f"only the network's original path)", rows)
    best = min(rows, key=lambda r: r["fast_p50"])
    best_threads = best["threads"]
    # Every alternative at its own best setting (93cd59e had the workers parameter too).
    today = min(rows, key=lambda r: r["original_p50"])
    today_net = min(rows, key=lambda r: r["orig_net_p50"])
    stage_table = [{"stage": s, "original_p50": headline[today["threads"]]["original_stages_ms"][s],
                    "orig_net_p50": headline[today_net["threads"]]["orig_net_stages_ms"][s],
                    "fast_p50": headline[best_threads]["fast_stages_ms"][s]} for s in (*STAGES, "total_ms")]
    print_table(f"stage breakdown (median ms): original at its best setting ({today['threads']}), orig_net at "
                f"its best ({today_net['threads']}), fast at its best ({best_threads})", stage_table)
    fast_stages = headline[best_threads]["fast_stages_ms"]
    filter_share = fast_stages["filter_ms"] / max(fast_stages["complete_ms"], 1e-9)

    # ---- 2. scaling (fast path, best thread setting)
    workers, threads = settings[[thread_label(s) for s in settings].index(best_threads)]
    torch.set_num_threads(threads)
    if hasattr(pipeline.completer, "workers"):
        pipeline.completer.workers = workers
    pipeline.config = dataclasses.replace(pipeline.config, workers=workers)
    configs = [(int(c), args.points) for c in args.scale_cars.split(",") if c.strip()]
    configs += [(args.cars, int(p)) for p in args.scale_points.split(",") if p.strip() and int(p) != args.points]
    if args.scale_repeat < 1:
        configs = []
    scaling = []
    for cars, points in configs:
        msg, det_msg, nc, npts = frame_messages(base, cars, points, args.seed, classes)
        for _ in range(2):
            one_frame(pipeline, msg, det_msg, classes)
        samples_s = [one_frame(pipeline, msg, det_msg, classes)[0] for _ in range(args.scale_repeat)]
        totals = summary_ms(np.array([s["total_ms"] for s in samples_s]) / 1e3)
        scaling.append({"cars": nc, "points": npts, "p50_ms": totals["median_ms"], "p95_ms": totals["p95_ms"],
                        **{k.replace("_ms", ""): v for k, v in stage_rows(samples_s).items() if k != "total_ms"}})
    if scaling:
        print_table(f"scaling, fast path, threads {best_threads} (median ms per stage, "
                    f"{args.scale_repeat} frames per row)", scaling)

    load_after = load_average()
    speedup = today["original_p50"] / best["fast_p50"]
    speedup_net = today_net["orig_net_p50"] / best["fast_p50"]
    p95 = best["fast_p95"]
    results = {
        "cars": n_cars, "points": n_points, "backend": args.backend, "weights": weights,
        "messages": "rclpy" if classes is not None else "rosbags",
        "output_max_abs_diff_m": max_diff, "threads": headline, "best_threads": best_threads,
        "p50_ms": best["fast_p50"], "p95_ms": p95,
        "original_p50_ms": today["original_p50"], "original_threads": today["threads"],
        "speedup_p50": speedup, "speedup_same_setting": {r["threads"]: r["speedup_p50"] for r in rows},
        "orig_net_p50_ms": today_net["orig_net_p50"], "speedup_vs_orig_net_p50": speedup_net,
        "filter_share_of_complete": filter_share,
        "stages_ms": stage_table, "scaling": scaling,
        "cpu_count": os.cpu_count(), "load_average_before": load_before, "load_average_after": load_after,
        "targets": {"speedup_min": TARGET_SPEEDUP, "p95_ms_max_idle": TARGET_P95_MS,
                    "speedup_met": bool(speedup >= TARGET_SPEEDUP),
                    "filter_share_max": TARGET_FILTER_SHARE,
                    "filter_share_met": bool(filter_share <= TARGET_FILTER_SHARE),
                    "p95_met_here": bool(p95 <= TARGET_P95_MS)},
    }
    print(f"\n{n_cars} cars, {n_points} points: fast (threads {best_threads}) p50 {results['p50_ms']:.1f} ms, "
          f"p95 {p95:.1f} ms; today's pipeline at its best setting ({today['threads']}) p50 "
          f"{results['original_p50_ms']:.1f} ms -> {speedup:.2f}x "
          f"(target >= {TARGET_SPEEDUP}x: {'met' if speedup >= TARGET_SPEEDUP else 'NOT met'}); "
          f"p95 target <= {TARGET_P95_MS:.0f} ms on an idle 2-core machine: "
          f"{'met' if p95 <= TARGET_P95_MS else 'not met'} here. Conservative (only the network's original path): "
          f"{today_net['orig_net_p50']:.1f} ms -> {speedup_net:.2f}x. Filter stage {fast_stages['filter_ms']:.1f} ms = "
          f"{100 * filter_share:.0f} % of completion {fast_stages['complete_ms']:.1f} ms (target <= "
          f"{100 * TARGET_FILTER_SHARE:.0f} %: {'met' if filter_share <= TARGET_FILTER_SHARE else 'NOT met'}); "
          f"outputs equal (completed clouds within {max_diff:.1e} m).")
    print(f"load average (1 min) before / after: {load_before[0]:.2f} / {load_after[0]:.2f} on {os.cpu_count()} "
          "cores (whether the machine was idle: the other-processes line below)")
    return results
