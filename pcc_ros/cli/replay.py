"""``pcc replay``: the node core itself over a bag — what a live node would publish, recorded.

The command half of :mod:`pcc_ros.runtime.bag_replay`: the flags, the
:class:`~pcc_ros.runtime.bag_replay.ReplayConfig` built from them, and the timing table.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from pcc_ros.runtime.bag_replay import ReplayConfig, replay
from pcc_ros.tables import print_table


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("bag", type=Path, help="input rosbag2 (MCAP or sqlite3)")
    parser.add_argument("--out", type=Path, required=True, help="output bag: a folder (rosbag2 writes metadata.yaml "
                        "and NAME.mcap / NAME.db3 inside it)")
    parser.add_argument("--config", type=Path,
                        help="node parameter YAML (default: the shipped completion.yaml; with --filter "
                        "detection_filter.yaml)")
    parser.add_argument("--backend", help="override the config's backend")
    parser.add_argument("--checkpoint", help="override the config's checkpoint")
    parser.add_argument("--device", help="auto | cpu | cuda | cuda:N")
    parser.add_argument(
        "--score-mapping", choices=("identity", "sigmoid"),
        help="override the config's score_mapping (sigmoid for logits, e.g. PointRCNN)",
    )
    parser.add_argument("--filter", action="store_true",
                        help="run with the detection filter node's parameters and also record its outputs "
                        "(/detections_filtered, /detections_rejected, /filter_markers)")
    parser.add_argument("--points-topic", default="/points", help="PointCloud2 topic of the bag (default /points)")
    parser.add_argument("--detections-topic", default="/detections",
                        help="Detection3DArray topic (default /detections; /ground_truth completes the labelled boxes)")
    parser.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap",
                        help="output bag storage (default mcap)")
    parser.add_argument("--no-copy-inputs", action="store_true", help="write only the pipeline outputs")
    parser.add_argument("--force", action="store_true", help="replace an existing output bag")


def run(args: argparse.Namespace) -> int:
    opts = ReplayConfig(
        bag=args.bag, out=args.out, config=args.config, backend=args.backend, checkpoint=args.checkpoint,
        device=args.device, score_mapping=args.score_mapping, with_filter=args.filter,
        points_topic=args.points_topic, detections_topic=args.detections_topic, storage=args.storage,
        copy_inputs=not args.no_copy_inputs, force=args.force,
    )
    summary, parameters = replay(opts)
    print_table(f"replay timing per frame ({summary.frames} frames, backend {parameters['backend']})",
                summary.latency_table())
    print(
        ("\n" + (f"kept {summary.kept}, rejected {summary.rejected} detections" if args.filter
                 else "detections not judged (the completion node runs no filter; --filter judges them)"))
        + f"; skipped frames {summary.skipped_frames}; "
        f"undecodable messages {summary.undecodable} (left out of the output); "
        f"unpaired clouds {summary.unpaired_clouds}, unpaired detection arrays {summary.unpaired_detections}"
    )
    print(f"wrote {opts.out}")
    return 0
