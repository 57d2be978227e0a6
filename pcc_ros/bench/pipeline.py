"""Per-frame latency of the whole pipeline, as a node runs it, for a 64-beam frame with 20 cars.

A full-resolution SynthCars frame (HDL-64E-like, ~110k points) with 20 car detections goes
through ``Pipeline.process_messages`` + ``build_outputs`` (decode, crop, canonicalise,
complete, filter, encode) repeatedly. The same frame through the ``input`` backend (no
network) is the baseline measured in the same process, so the ratio isolates the backend.
Target: p95 <= 100 ms (10 Hz LiDAR) on 2 cores with the default backend.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from pcc_ros.bench.common import print_table

STAGES = ("decode_ms", "crop_ms", "complete_ms", "filter_ms", "uncanonical_ms", "encode_ms")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--backend", default="pointpncnet", help="backend under test")
    parser.add_argument("--checkpoint", help="checkpoint (default: shipped weights; untrained if none)")
    parser.add_argument("--cars", type=int, default=20, help="car detections in the frame")
    parser.add_argument("--repeat", type=int, default=40, help="timed frames")


def synth_frame(seed: int, cars: int):
    """One full-resolution SynthCars frame as messages: (PointCloud2, Detection3DArray, n_cars)."""
    from pcc_ros.data.kitti import KittiTracking
    from pcc_ros.data.synthetic import generate
    from pcc_ros.msg.detections import detection_array_from_boxes
    from pcc_ros.msg.pointcloud2 import create_cloud

    with tempfile.TemporaryDirectory() as tmp:
        generate(tmp, sequences=1, frames=1, seed=seed, progress=False)
        frame = next(KittiTracking(Path(tmp) / "training").frames("0000"))
    gt = frame.ground_truth
    vehicles = gt[np.array([str(lbl) in ("Car", "Van") for lbl in gt.label]) & gt.valid_mask()]
    order = np.argsort(np.linalg.norm(vehicles.center[:, :2], axis=1))  # the nearest cars, like a detector
    dets = vehicles[order[:cars]]
    cloud = create_cloud(frame.points, frame.fields, frame.frame_id, frame.stamp_ns)
    return cloud, detection_array_from_boxes(dets, frame.frame_id, frame.stamp_ns), len(dets), len(frame.points)


def time_pipeline(pipeline, cloud, dets, repeat: int) -> dict[str, np.ndarray]:
    from pcc_ros.pipeline import build_outputs

    for _ in range(3):  # warm-up (allocator, thread pools)
        result, originals = pipeline.process_messages(cloud, dets)
        build_outputs(result, originals)
    stages: dict[str, list[float]] = {s: [] for s in (*STAGES, "total_ms")}
    for _ in range(repeat):
        tic = time.perf_counter()
        result, originals = pipeline.process_messages(cloud, dets)
        enc = time.perf_counter()
        build_outputs(result, originals)
        done = time.perf_counter()
        for stage in STAGES[:-1]:
            stages[stage].append(result.timings_ms.get(stage, 0.0))
        stages["encode_ms"].append((done - enc) * 1e3)
        stages["total_ms"].append((done - tic) * 1e3)
    return {k: np.asarray(v) for k, v in stages.items()}


def _make_pipeline(backend: str, checkpoint: str | None):
    from pcc_ros.models.base import create, default_checkpoint, get_backend, load_completer
    from pcc_ros.pipeline import Pipeline, PipelineConfig

    config = PipelineConfig(backend=backend, device="cpu", min_points=5, max_instances=64)
    cls = get_backend(backend)
    trained = not cls.learned or checkpoint or default_checkpoint(backend)
    completer = load_completer(backend, checkpoint, device="cpu") if trained else create(backend, device="cpu")
    return Pipeline(config, completer=completer), bool(trained)


def run(args: argparse.Namespace) -> dict:
    import torch

    torch.manual_seed(args.seed)
    cloud, dets, n_cars, n_points = synth_frame(args.seed, args.cars)
    threads = torch.get_num_threads()
    rows, timings = [], {}
    results = {"cars": n_cars, "points": n_points, "backend": args.backend, "threads": threads}
    for name in ("input", args.backend):
        pipeline, trained = _make_pipeline(name, args.checkpoint if name == args.backend else None)
        timings[name] = time_pipeline(pipeline, cloud, dets, args.repeat)
        if name == args.backend:
            results["weights"] = "trained" if trained else "untrained (same cost)"
    base, ours = timings["input"], timings[args.backend]
    for stage in (*STAGES, "total_ms"):
        rows.append({
            "stage": stage,
            "input_p50": float(np.percentile(base[stage], 50)),
            f"{args.backend}_p50": float(np.percentile(ours[stage], 50)),
            f"{args.backend}_p95": float(np.percentile(ours[stage], 95)),
        })
        results[stage.replace("_ms", "_p50_ms")] = float(np.percentile(ours[stage], 50))
    results["p50_ms"] = float(np.percentile(ours["total_ms"], 50))
    results["p95_ms"] = float(np.percentile(ours["total_ms"], 95))
    results["baseline_input_p50_ms"] = float(np.percentile(base["total_ms"], 50))
    results["ratio_vs_input"] = results["p50_ms"] / results["baseline_input_p50_ms"]
    print_table(
        f"pipeline per frame: {n_points} points, {n_cars} cars, {torch.get_num_threads()} threads "
        f"({results['weights']} {args.backend})", rows)
    print(f"\np50 {results['p50_ms']:.1f} ms, p95 {results['p95_ms']:.1f} ms "
          f"({results['ratio_vs_input']:.2f}x the input-backend pipeline); target p95 <= 100 ms")
    return results
