"""A 128-beam street at 20 Hz: 260k points / 40 cars / 80 boxes beside 120k / 20 / 20, one run.

The shipped filter node's configuration (``config/detection_filter.yaml``: pointpncnet with its
trained weights, ``workers`` 2, ``max_instances`` 64, ``decode_density`` 2, the evidence rule;
``device`` cpu) runs frame after frame on two frames built from one full-resolution SynthCars
scan (``pcc bench pipeline``'s frames): a 64-beam frame, 120k points with 20 car detections, and
a 128-beam frame, the scan with jittered copies to 260k points with 40 car detections (the
labelled vehicles, then car-sized boxes on random returns) and 40 more boxes of pedestrians and
cyclists (80 boxes: the filter passes those on unjudged, as it does on a street). Each frame
goes through ``Pipeline.process_messages`` and the filter node's data outputs
(``detections_filtered``, ``detections_rejected``; a node builds its markers only for a viewer)
in the message classes a node uses. Per row: per-stage median, p50 / p95 / max of the whole
frame (wall) and the median CPU time of the process per frame (every thread: what a shared
machine stretches least, so the linearity verdict uses it), the peak resident memory while the
setting's first frames ran (``/proc/self/status`` sampled every 5 ms) and how much it grew over
the process before them, and the detections judged / passed on. The rows run interleaved frame
by frame (load on a shared machine hits all alike).

Then the settings that trade speed for something else, at 260k / 80: ``workers`` 1 (one
core), ``max_instances`` 16 (the 16 highest-scoring cars judged, the others passed on
unjudged), ``decode_density`` 1 (completions 1 / 2.25 as dense), both, and ``max_crop_work``
200000 (the shipped 100000 skips the lowest-scoring car of this street). The verdict says
whether the shipped setting holds 20 Hz (p95 <= 50 ms) on this machine, and which setting does,
and whether the cost grows no worse than linearly with the work (points, cars).
"""

from __future__ import annotations

import argparse
import os
import threading
import time

import numpy as np

from benchmarks.common import load_average, print_table, summary_ms

STAGES = ("decode_ms", "crop_ms", "complete_ms", "filter_ms", "uncanonical_ms", "encode_ms")
PERIOD_MS = 50.0  # 20 Hz
SIZES = ((120_000, 20, 0), (260_000, 40, 40))  # points, cars, other boxes
VARIANTS = (
    ("shipped", {}),
    ("workers 1", {"workers": 1}),
    ("max_instances 16", {"max_instances": 16}),
    ("decode_density 1", {"decode_density": 1}),
    ("max_instances 16 + decode_density 1", {"max_instances": 16, "decode_density": 1}),
    ("max_crop_work 200000", {"max_crop_work": 200_000}),
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--repeat", type=int, default=30, help="timed frames per row (default 30)")
    parser.add_argument("--warmup", type=int, default=3, help="untimed frames before each row (default 3)")
    parser.add_argument("--variants", default=",".join(name for name, _ in VARIANTS[1:]),
                        help="settings tried at 260k / 80 besides the shipped one ('' = none)")


def rss_mb() -> float:
    """This process's resident memory now (MB)."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


class PeakRss:
    """The highest resident memory while the block runs (sampled by a thread every ``period_s``)."""

    def __init__(self, period_s: float = 0.005) -> None:
        self.period_s, self.peak, self.before = period_s, 0.0, 0.0
        self._stop = threading.Event()

    def _sample(self) -> None:
        while not self._stop.wait(self.period_s):
            self.peak = max(self.peak, rss_mb())

    def __enter__(self) -> PeakRss:
        self.before = self.peak = rss_mb()
        self._thread = threading.Thread(target=self._sample, daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()
        self.peak = max(self.peak, rss_mb())


def other_boxes(points: np.ndarray, n: int, rng: np.random.Generator):
    """``n`` pedestrian / cyclist boxes standing on random above-ground returns."""
    from pcc_ros.types import Boxes

    xyz = points[:, :3].astype(np.float64)
    dist = np.linalg.norm(xyz[:, :2], axis=1)
    near = xyz[(dist > 3.0) & (dist < 40.0) & (xyz[:, 2] > -1.2)]
    centres = near[rng.choice(len(near), n, replace=len(near) < n)]
    cyclist = rng.random(n) < 0.5
    size = np.where(cyclist[:, None], [1.8, 0.6, 1.7], [0.8, 0.6, 1.75])
    centres[:, 2] = -1.73 + size[:, 2] / 2.0
    return Boxes(centres, size, rng.uniform(-np.pi, np.pi, n),
                 label=np.where(cyclist, "Cyclist", "Pedestrian").astype(object), score=rng.uniform(0.3, 0.9, n))


def street(base, points: int, cars: int, others: int, seed: int, classes):
    """(PointCloud2, Detection3DArray) of one frame: the scan resized, ``cars`` car boxes, ``others`` more."""
    from benchmarks.pipeline import car_boxes, resize_scan
    from pcc_ros.msg.detections import detection_array_from_boxes
    from pcc_ros.msg.pointcloud2 import create_cloud
    from pcc_ros.types import Boxes

    scan, fields, vehicles, frame_id, stamp = base
    rng = np.random.default_rng(seed)
    scan = resize_scan(scan, points, rng)
    boxes = car_boxes(scan, vehicles, cars, rng)
    if others:
        boxes = Boxes.concatenate([boxes, other_boxes(scan, others, rng)])
    return create_cloud(scan, fields, frame_id, stamp, classes), detection_array_from_boxes(boxes, frame_id, stamp,
                                                                                            classes)


def shipped_pipeline(**overrides):
    """The pipeline of the shipped filter node's file, on the CPU (``overrides``: node parameters)."""
    from pcc_ros.pipeline.config import load_parameters, pipeline_config
    from pcc_ros.pipeline.core import Pipeline

    values = load_parameters(None, True, device="cpu", **overrides)
    return Pipeline(pipeline_config(values)), values


def node_frame(pipeline, cloud, dets, classes) -> tuple[dict[str, float], object]:
    """One frame as the filter node runs it without a viewer: per-stage and total ms, and the result."""
    from pcc_ros.pipeline.outputs import build_outputs

    cpu = time.process_time()
    tic = time.perf_counter()
    result, originals = pipeline.process_messages(cloud, dets)
    enc = time.perf_counter()
    build_outputs(result, originals, classes, names=["detections_filtered", "detections_rejected"])
    done = time.perf_counter()
    stages = {s: result.timings_ms.get(s, 0.0) for s in STAGES[:-1]}
    stages["encode_ms"] = (done - enc) * 1e3
    stages["total_ms"] = (done - tic) * 1e3
    stages["cpu_ms"] = (time.process_time() - cpu) * 1e3  # every thread of the process
    return stages, result


def memory(pipeline, cloud, dets, classes, frames: int = 3) -> dict[str, float]:
    """Peak resident memory while a setting's first ``frames`` frames run, and its growth over the process
    before them (the work arrays it adds; settings measured one after the other, smallest first, so a
    later one counts only what the earlier ones did not already allocate)."""
    with PeakRss() as rss:
        for _ in range(frames):
            node_frame(pipeline, cloud, dets, classes)
    return {"peak_rss_mb": rss.peak, "rss_growth_mb": rss.peak - rss.before}


def row_of(name: str, samples: list, mem: dict) -> dict:
    """One table row from the ``(stages, result)`` samples of a setting."""
    totals = summary_ms(np.array([s["total_ms"] for s, _ in samples]) / 1e3)
    result = samples[-1][1]
    status = np.asarray(result.status)
    return {
        "setting": name,
        "p50_ms": totals["median_ms"], "p95_ms": totals["p95_ms"], "max_ms": totals["max_ms"],
        "cpu_p50_ms": float(np.median([x["cpu_ms"] for x, _ in samples])),
        "cpu_bound_hz": (os.cpu_count() or 1) * 1e3 / max(float(np.median([x["cpu_ms"] for x, _ in samples])), 1e-9),
        **{s.replace("_ms", ""): float(np.median([x[s] for x, _ in samples])) for s in STAGES},
        "judged": int(np.isin(status, ["kept", "rejected"]).sum()), "passed_on": int((status == "skipped").sum()),
        "skipped": dict(result.skipped), **mem, "holds_20hz": bool(totals["p95_ms"] <= PERIOD_MS),
    }


def run(args: argparse.Namespace) -> dict:
    import torch

    from benchmarks.pipeline import base_frame, node_classes
    from pcc_ros.runtime.heap import freeze_long_lived

    load_before = load_average()
    classes = node_classes()
    base = base_frame(args.seed)
    frames = {}
    for points, cars, others in SIZES:
        cloud, dets = street(base, points, cars, others, args.seed, classes)
        frames[(points, cars, others)] = (cloud, dets)
    wanted = [v.strip() for v in args.variants.split(",") if v.strip()]
    unknown = sorted(set(wanted) - {name for name, _ in VARIANTS})
    if unknown:
        raise SystemExit(f"unknown variant(s) {unknown}; known: {[name for name, _ in VARIANTS[1:]]}")
    big = SIZES[-1]
    # rows: (name, size, pipeline, torch threads); all loaded first, then timed interleaved
    pipeline, values = shipped_pipeline()
    settings = [("shipped", size, pipeline, values) for size in SIZES]
    settings += [(name, big, *shipped_pipeline(**overrides)) for name, overrides in VARIANTS[1:] if name in wanted]
    freeze_long_lived()  # as the node does once started

    def frame(k: int):
        _, size, pipe, v = settings[k]
        torch.set_num_threads(1 if int(v["workers"]) > 1 else 2)  # workers x 1 thread, or torch's 2
        return node_frame(pipe, *frames[size], classes)

    mems = []
    for _, size, pipe, v in settings:  # memory: one setting at a time
        torch.set_num_threads(1 if int(v["workers"]) > 1 else 2)
        mems.append(memory(pipe, *frames[size], classes))
    for _ in range(args.warmup):
        for k in range(len(settings)):
            frame(k)
    samples: list[list] = [[] for _ in settings]
    for r in range(args.repeat):  # interleaved, order alternating: load on a shared machine hits every row alike
        for k in (range(len(settings)) if r % 2 == 0 else reversed(range(len(settings)))):
            samples[k].append(frame(k))
    rows = [{"points": size[0], "cars": size[1], "boxes": size[1] + size[2], **row_of(name, samples[k], mems[k])}
            for k, (name, size, _, _) in enumerate(settings)]
    columns = ("setting", "points", "cars", "boxes", "p50_ms", "p95_ms", "max_ms", "cpu_p50_ms", "cpu_bound_hz",
               "decode", "crop",
               "complete", "filter", "uncanonical", "encode", "judged", "passed_on", "peak_rss_mb", "rss_growth_mb")
    table = [{k: r[k] for k in columns} for r in rows]
    print_table(f"filter node (shipped config/detection_filter.yaml, cpu), {args.repeat} frames per row, rows "
                "interleaved frame by frame; ms, MB (memory: each setting alone)",
                table)
    small, large = rows[0], rows[1]
    work = {"points": large["points"] / small["points"], "cars": large["cars"] / small["cars"],
            "boxes": large["boxes"] / small["boxes"]}
    ratio = large["cpu_p50_ms"] / small["cpu_p50_ms"]  # CPU time: what a loaded machine stretches least
    linear = bool(ratio <= max(work.values()))
    holds = [r["setting"] for r in rows[1:] if r["holds_20hz"]]
    can = [r["setting"] for r in rows[1:] if r["cpu_bound_hz"] >= 1e3 / PERIOD_MS]
    verdict = (f"260k points / {large['boxes']} boxes: shipped p95 {large['p95_ms']:.1f} ms -> 20 Hz "
               f"{'holds' if large['holds_20hz'] else 'does NOT hold'} here (wall); settings that hold it: "
               f"{', '.join(holds) if holds else 'none of those tried'}. CPU per frame {large['cpu_p50_ms']:.0f} ms: "
               f"{os.cpu_count()} cores sustain at most {large['cpu_bound_hz']:.1f} Hz; settings whose CPU time "
               f"allows 20 Hz on {os.cpu_count()} cores: {', '.join(can) if can else 'none of those tried'}. "
               f"CPU time {ratio:.2f}x the 120k / 20 frame's for {work['points']:.2f}x the points, "
               f"{work['cars']:.1f}x the cars and {work['boxes']:.0f}x the boxes: "
               f"{'no worse than linear' if linear else 'WORSE than linear'}.")
    print("\n" + verdict)
    return {"rows": rows, "work_ratio": work, "cpu_ratio_p50": ratio, "no_worse_than_linear": linear,
            "period_ms": PERIOD_MS, "settings_holding_20hz": holds, "settings_cpu_allows_20hz": can,
            "verdict": verdict,
            "shipped_parameters": {k: values[k] for k in ("backend", "workers", "max_instances", "decode_density",
                                                          "max_crop_work", "min_points", "rule")},
            "messages": "rclpy" if classes is not None else "rosbags", "cpu_count": os.cpu_count(),
            "load_average_before": load_before, "load_average_after": load_average()}
