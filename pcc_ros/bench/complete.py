"""Completion speed and memory of a backend at batch 1, 8 and 32 (``pcc bench complete``).

Each configuration runs in a fresh process so its peak memory is its own (CPU: peak
resident set size; CUDA: peak allocated device memory). The ``mirror`` baseline is measured
the same way in the same run, as the ratio's reference. Inputs are car-like canonical
clouds of ``--points`` points (or, with ``--data``, real instances of an instance cache,
cycled in order), i.e. the sizes a detector crop actually has, not a resampled 3096.

Targets (issue: 20 cars in the pipeline's 100 ms frame budget on a 2-core CPU): PointPnCNet
``default`` >= 200 instances/s at batch 32 and <= 20 ms for one instance.

JSON: the first configuration's figures at the top level (``instances_per_s_b1``,
``instances_per_s_b8``, ``instances_per_s_b32``, ``latency_ms_b1``, ``peak_memory_mb``), every
configuration under ``configs``, the baseline under ``baseline``.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import resource
from pathlib import Path
from typing import Any

import numpy as np

from pcc_ros.bench.common import median_ms, print_table

BATCHES = (1, 8, 32)
TARGET_B32 = 200.0
TARGET_LATENCY_MS = 20.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--backend", default="pointpncnet", help="registered completion backend")
    parser.add_argument(
        "--sizes", default=None,
        help="comma-separated size presets of the backend (default: all it has, e.g. default,paper)",
    )
    parser.add_argument("--checkpoint", type=Path, help="weights (default: shipped ones; else untrained)")
    parser.add_argument("--points", type=int, default=512, help="points per synthetic input cloud (default 512)")
    parser.add_argument("--data", type=Path, help="instance cache: use its real instances as inputs instead")
    parser.add_argument("--device", default="cpu", help="cpu | cuda | auto (default cpu)")
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's)")
    parser.add_argument("--repeat", type=int, default=20, help="timed runs per batch size (default 20)")


def car_clouds(count: int, points: int, seed: int) -> list[np.ndarray]:
    """Car-like canonical clouds: points on the visible side and top of a car-sized box."""
    rng = np.random.default_rng(seed)
    clouds = []
    for _ in range(count):
        pts = rng.uniform(-1, 1, (points, 3))
        face = rng.choice([1, 2], points)  # the sensor-facing side (+y) and the top (+z)
        pts[np.arange(points), face] = 1.0
        clouds.append((pts * [0.5, 0.2, 0.15] + rng.normal(0, 0.003, (points, 3))).astype(np.float32))
    return clouds


def cache_clouds(path: Path, count: int) -> list[np.ndarray]:
    from pcc_ros.data.instances import InstanceCache

    cache = InstanceCache.load(path)
    idx = cache.indices("test") if len(cache.indices("test")) else np.arange(len(cache))
    return [np.array(cache.points(int(i)), dtype=np.float32) for i in idx[:count]]


def _peak_memory_mb(device: Any) -> float:
    import torch

    if device.type == "cuda":
        return torch.cuda.max_memory_allocated(device) / 2**20
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: kB


def measure(spec: dict[str, Any]) -> dict[str, Any]:
    """Time one backend configuration (runs in its own process)."""
    import torch

    from pcc_ros.models import get_backend, load_completer

    if spec["threads"]:
        torch.set_num_threads(spec["threads"])
    rss_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    cls = get_backend(spec["backend"])
    kwargs = {"size": spec["size"]} if spec["size"] else {}
    if cls.learned and spec["checkpoint"]:
        completer = load_completer(spec["backend"], spec["checkpoint"], device=spec["device"])
        weights = str(spec["checkpoint"])
    else:
        torch.manual_seed(0)
        completer = cls(device=spec["device"], **kwargs) if cls.learned else cls(device=spec["device"])
        weights = "untrained (speed only)" if cls.learned else "none"
    device = getattr(completer, "device", torch.device("cpu"))
    clouds = spec["clouds"]
    row: dict[str, Any] = {
        "backend": spec["backend"], "size": spec["size"] or "-", "weights": weights,
        "points_in_mean": float(np.mean([len(c) for c in clouds])), "threads": torch.get_num_threads(),
    }
    for b in BATCHES:
        if hasattr(completer, "batch_size"):
            completer.batch_size = b
        batch = [clouds[i % len(clouds)] for i in range(b)]
        repeat = max(3, spec["repeat"] if b < 32 else spec["repeat"] // 2)
        ms = median_ms(lambda batch=batch: completer.complete(batch), repeat=repeat, warmup=2)
        row[f"instances_per_s_b{b}"] = b / (ms / 1e3)
        if b == 1:
            row["latency_ms_b1"] = ms
    row["points_out"] = len(completer.complete(clouds[:1])[0])
    row["peak_memory_mb"] = _peak_memory_mb(device)
    row["memory_before_model_mb"] = rss_before
    if hasattr(completer, "model"):
        row["parameters"] = int(sum(p.numel() for p in completer.model.parameters()))
    row["device"] = str(device)
    return row


def _in_fresh_process(spec: dict[str, Any]) -> dict[str, Any]:
    ctx = mp.get_context("spawn")
    with ctx.Pool(1) as pool:
        return pool.apply(measure, (spec,))


def sizes_of(backend: str, requested: str | None) -> list[str | None]:
    """Size presets to benchmark: the requested ones, else all the backend module defines."""
    import importlib

    from pcc_ros.models import get_backend

    if requested:
        return [s.strip() for s in requested.split(",") if s.strip()]
    presets = getattr(importlib.import_module(get_backend(backend).__module__), "PRESETS", None)
    return list(presets) if presets else [None]


def run(args: argparse.Namespace) -> dict:
    from pcc_ros.models import default_checkpoint, get_backend

    count = max(BATCHES)
    clouds = cache_clouds(args.data, count) if args.data else car_clouds(count, args.points, args.seed)
    if not clouds:
        raise SystemExit(f"{args.data}: no instances to benchmark with")
    sizes = sizes_of(args.backend, args.sizes)
    if "default" in sizes:  # the target applies to the default size: measure it first
        sizes.remove("default")
        sizes.insert(0, "default")
    cls = get_backend(args.backend)
    base = {"backend": args.backend, "device": args.device, "threads": args.threads, "repeat": args.repeat,
            "clouds": clouds}
    rows = []
    for size in sizes:
        checkpoint = args.checkpoint
        if cls.learned and checkpoint is None and size in ("default", None):
            checkpoint = default_checkpoint(args.backend)  # the shipped weights are the default size
        rows.append(_in_fresh_process({**base, "size": size, "checkpoint": checkpoint}))
    baseline = _in_fresh_process({**base, "backend": "mirror", "size": None, "checkpoint": None})
    for row in rows:
        row["vs_mirror_b32"] = row["instances_per_s_b32"] / baseline["instances_per_s_b32"]
    table = [*rows, {**baseline, "vs_mirror_b32": 1.0}]
    print_table(
        f"pcc bench complete ({args.device}, inputs: "
        f"{'cache ' + str(args.data) if args.data else f'{args.points}-point car-like clouds'})",
        table,
        ["backend", "size", "points_in_mean", "points_out", "instances_per_s_b1", "instances_per_s_b8",
         "instances_per_s_b32", "latency_ms_b1", "peak_memory_mb", "vs_mirror_b32"],
    )
    first = rows[0]
    results: dict[str, Any] = {k: v for k, v in first.items()}
    results["configs"] = {str(r["size"]): r for r in rows}
    results["baseline"] = baseline
    results["inputs"] = str(args.data) if args.data else f"car-like clouds, {args.points} points"
    if first["size"] == "default":
        results["targets"] = {
            "instances_per_s_b32_min": TARGET_B32,
            "latency_ms_b1_max": TARGET_LATENCY_MS,
            "met": bool(first["instances_per_s_b32"] >= TARGET_B32 and first["latency_ms_b1"] <= TARGET_LATENCY_MS),
        }
        print(f"\ntarget (default): >= {TARGET_B32:.0f} inst/s at batch 32 and <= {TARGET_LATENCY_MS:.0f} ms "
              f"at batch 1: {'met' if results['targets']['met'] else 'NOT met'}")
    return results
