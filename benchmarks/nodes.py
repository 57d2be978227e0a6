"""Each node's own work: per-stage time and memory of the completion and filter nodes, every stage vs their own.

Before, both nodes ran the whole pipeline (complete and filter); now each runs the stages its
outputs and rule need (:func:`pcc_ros.runtime.node.pipeline_stages`): the filter node with the
shipped rule (evidence, ``w_mismatch`` 0) loads no completion network, the completion node runs
no filter. Each variant runs in a fresh process (its memory its own): the node's pipeline from
the shipped YAML (CPU), then the real KITTI tracking frames (``../shared/data``, full scans with
their PointRCNN detections, logits: ``score_mapping`` sigmoid) through ``process_messages``, as
the node does. Reported: the median of each stage over the frames after the first, the resident
memory after loading and at the end (``/proc/self/status`` VmRSS / VmHWM), and that the node's
published decisions (filter) and completed clouds (completion) are the same both ways.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared" / "data" / "kitti_tracking"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--frames", type=int, default=20, help="KITTI frames per variant")


def _rss_mb() -> dict[str, float]:
    values = {}
    for line in Path("/proc/self/status").read_text().splitlines():
        key, _, rest = line.partition(":")
        if key in ("VmRSS", "VmHWM"):
            values[key] = float(rest.split()[0]) / 1024
    return values


def measure(mode: str, own: bool, frames: int) -> dict:
    """One variant in this process: the node's pipeline, ``own`` stages or every stage."""
    import hashlib

    import numpy as np

    from pcc_ros.data.kitti import KittiTracking
    from pcc_ros.msg.detections import detection_array_from_boxes
    from pcc_ros.msg.pointcloud2 import create_cloud
    from pcc_ros.pipeline.config import load_parameters, pipeline_config
    from pcc_ros.pipeline.core import Pipeline
    from pcc_ros.runtime.node import output_names, pipeline_stages

    values = load_parameters(with_filter=mode == "filter", device="cpu", score_mapping="sigmoid")
    stages = pipeline_stages(output_names(mode)) if own else {"completes": True, "filters": True}
    pipeline = Pipeline(pipeline_config(values), **stages)
    loaded = _rss_mb()
    data = list(KittiTracking(SHARED / "training").frames("0000", detections_dir=SHARED / "detections" / "pointrcnn"))
    timings: dict[str, list[float]] = {}
    digest = hashlib.sha256()
    for frame in (data * (frames // len(data) + 1))[:frames]:
        cloud = create_cloud(frame.points, list(frame.fields), frame.frame_id, frame.stamp_ns)
        dets = detection_array_from_boxes(frame.detections, frame.frame_id, frame.stamp_ns)
        result, _ = pipeline.process_messages(cloud, dets, with_originals=False)
        for key, ms in result.timings_ms.items():
            timings.setdefault(key, []).append(ms)
        if mode == "filter":  # what the filter node publishes: its decisions
            digest.update(np.asarray(result.status, dtype=str).tobytes())
        else:  # what the completion node publishes: the completed cloud
            digest.update(np.round(result.completed_points, 4).tobytes())
    return {"mode": mode, "own_stages": own, "completer_loaded": pipeline.completer is not None,
            "stage_median_ms": {k: float(np.median(v[1:] if len(v) > 1 else v)) for k, v in timings.items()},
            "rss_loaded_mb": loaded["VmRSS"], "rss_peak_mb": _rss_mb()["VmHWM"], "outputs_sha256": digest.hexdigest()}


def run(args: argparse.Namespace) -> dict:
    from pcc_ros.tables import print_table

    results, rows = [], []
    for mode in ("completion", "filter"):
        for own in (False, True):
            code = ("import json, sys; sys.path.insert(0, sys.argv[1]); from benchmarks.nodes import measure; "
                    "print(json.dumps(measure(sys.argv[2], sys.argv[3] == '1', int(sys.argv[4]))))")
            out = subprocess.run([sys.executable, "-c", code, str(REPO), mode, "1" if own else "0", str(args.frames)],
                                 capture_output=True, text=True, cwd=REPO)
            if out.returncode:
                raise SystemExit(f"{mode} ({'own' if own else 'all'} stages) failed:\n{out.stderr[-3000:]}")
            r = json.loads(out.stdout.strip().splitlines()[-1])
            results.append(r)
            st = r["stage_median_ms"]
            rows.append({"node": mode, "stages": "own" if own else "all (before)",
                         "network loaded": "yes" if r["completer_loaded"] else "no",
                         "complete ms": f"{st.get('complete_ms', 0.0):.1f}",
                         "filter ms": f"{st.get('filter_ms', 0.0):.1f}",
                         "total ms": f"{sum(st.values()):.1f}", "RSS loaded MB": f"{r['rss_loaded_mb']:.0f}",
                         "RSS peak MB": f"{r['rss_peak_mb']:.0f}"})
    print_table(f"per-node stages, {args.frames} KITTI frames (median after the first), fresh process each", rows)
    for mode in ("completion", "filter"):
        before, after = (r for r in results if r["mode"] == mode)
        same = before["outputs_sha256"] == after["outputs_sha256"]
        print(f"{mode} node: published outputs {'equal' if same else 'DIFFERENT'} with every stage and with its own")
        if not same:
            raise SystemExit(f"{mode}: outputs differ")
    return {"variants": results}
