"""Detection AP and the filter's operating curve against points-in-box and score (``pcc eval detections``).

The command half of :mod:`pcc_ros.workflows.detection_eval` (which says what is measured): flags in,
the library's loading, evaluation, report, plot and JSON out.
"""

from __future__ import annotations

import argparse
import logging
from collections.abc import Callable
from pathlib import Path

import numpy as np

from pcc_ros.files import write_json
from pcc_ros.pipeline.config import CONFIG_FILES
from pcc_ros.workflows.detection_eval import (
    build_pipeline,
    evaluate_detections,
    load_kitti,
    parse_frames,
    plot,
    print_report,
    to_json,
)

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--kitti", type=Path, help="KITTI tracking / object root (SynthCars: per-kind report)")
    source.add_argument(
        "--nuscenes", type=Path,
        help="nuScenes root (v1.0 tables): the cross-sensor check, no detector needed: car boxes on the annotated "
        "cars (true), car-sized boxes on every annotated non-vehicle and on sampled free ground (false), one score",
    )
    parser.add_argument("--score", type=float, default=0.7, help="--nuscenes: every box's detector score (0.7)")
    parser.add_argument("--ground-boxes", type=int, default=30, help="--nuscenes: free-ground boxes per frame (30)")
    parser.add_argument("--seed", type=int, default=0, help="--nuscenes: seed of the free-ground boxes (0)")
    parser.add_argument("--nms-iou", type=float, default=0.2,
                        help="--nuscenes: a false box overlapping a kept one above this BEV IoU is dropped, as a "
                        "detector's NMS would (0.2; 1: keep every box)")
    parser.add_argument("--detections", type=Path, help="detector results (default: ROOT/detections/synthetic)")
    parser.add_argument("--sequence", help="tracking sequence (needed when the root holds several)")
    parser.add_argument("--frames", help="START:STOP slice of the scans (default: all)")
    parser.add_argument("--config", type=Path, help=f"filter node YAML (default: the shipped {CONFIG_FILES['filter']})")
    parser.add_argument("--backend", help="override the completion backend (the evidence rule does not need it)")
    parser.add_argument("--score-mapping", choices=("identity", "sigmoid"), help="override score_mapping")
    parser.add_argument("--rule", choices=("evidence", "trapcc"), help="override the filter rule")
    parser.add_argument(
        "--gt-classes", default="Car",
        help="labels counted as Car (default: Car, KITTI's protocol: Vans ignored). 'Car,Van' scores vehicles",
    )
    parser.add_argument("--true-iou", type=float, default=0.3, help="BEV IoU that makes a detection true (0.3)")
    parser.add_argument("--max-lost", type=float, default=0.02, help="true-lost budget of the table (0.02)")
    parser.add_argument("--json", type=Path, help="write the results here")
    parser.add_argument("--plot", type=Path, help="PNG: operating curves and score distributions")


def _nuscenes(args: argparse.Namespace, pipeline) -> int:
    from pcc_ros.workflows.filter_check import check_json, nuscenes_check, plot_check, print_check

    result = nuscenes_check(args.nuscenes, pipeline, args.score, args.ground_boxes, args.seed, args.max_lost,
                            nms_iou=args.nms_iou)
    print_check(result)
    title = f"{args.nuscenes}: filter vs points-in-box, every box at score {args.score:g}, NMS IoU {args.nms_iou:g}"
    _write(args, lambda path: plot_check(result, path, title), lambda: check_json(result))
    return 0


def run(args: argparse.Namespace) -> int:
    if args.nuscenes is not None:
        pipeline = build_pipeline(args.config, {"backend": args.backend or "input", "score_mapping": args.score_mapping,
                                                "rule": args.rule})
        return _nuscenes(args, pipeline)
    detections = args.detections or (args.kitti / "detections" / "synthetic")
    frames = load_kitti(args.kitti, detections, args.sequence, parse_frames(args.frames))
    pipeline = build_pipeline(
        args.config, {"backend": args.backend, "score_mapping": args.score_mapping, "rule": args.rule}
    )
    gt_classes = tuple(c.strip() for c in args.gt_classes.split(",") if c.strip())
    results = evaluate_detections(frames, pipeline, gt_classes, args.true_iou, args.max_lost)
    title = f"{args.kitti} ({detections.name})"
    print_report(results, title)
    if all(np.isnan(v) for row in results["ap_before"].values() for v in row.values()):
        log.warning("no valid ground truth of %s: AP undefined (a sequence of Vans only? try --gt-classes Car,Van)",
                    "+".join(gt_classes))
    _write(args, lambda path: plot(results, path, title), lambda: to_json(results))
    return 0


def _write(args: argparse.Namespace, draw: Callable[[Path], None], payload: Callable[[], dict]) -> None:
    """The PNG (``--plot``) and the JSON (``--json``) a check asked for, each logged."""
    if args.plot:
        draw(args.plot)
        log.info("wrote %s", args.plot)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        write_json(args.json, payload(), indent=1, nonfinite_null=True)
        log.info("wrote %s", args.json)
