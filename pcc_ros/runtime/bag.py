"""``pcc replay``: run exactly the pipeline the nodes run over a bag, and record what they publish.

Scans and detections are paired by header stamp with the nodes' own
:class:`~pcc_ros.runtime.pairing.StampPairer`, each pair goes through
:meth:`~pcc_ros.pipeline.core.Pipeline.process_messages` and
:func:`~pcc_ros.pipeline.core.build_outputs`, and the outputs are written on the nodes'
topics and types. Offline nothing is dropped for lack of time: every pair is processed.

Failures: the output bag is written next to ``--out`` and renamed into place only after
every check passed (at least one frame processed); a message that does not deserialize is
skipped, counted and left out of the output (also of the copied input topics); a frame
the pipeline refuses is skipped and counted, as a node would.
"""

from __future__ import annotations

import argparse
import logging
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from pcc_ros.errors import DataError, PccError

log = logging.getLogger(__name__)

#: Output topic -> message type, as the nodes publish them.
COMPLETION_TOPICS = {
    "/completed": "sensor_msgs/msg/PointCloud2",
    "/completed_markers": "visualization_msgs/msg/MarkerArray",
}
FILTER_TOPICS = {
    "/detections_filtered": "vision_msgs/msg/Detection3DArray",
    "/detections_rejected": "vision_msgs/msg/Detection3DArray",
    "/filter_markers": "visualization_msgs/msg/MarkerArray",
}


@dataclass
class ReplaySummary:
    frames: int = 0
    skipped_frames: int = 0
    unpaired_clouds: int = 0
    unpaired_detections: int = 0
    kept: int = 0
    rejected: int = 0
    undecodable: int = 0
    first_skip_reason: str = ""
    timings_ms: dict[str, list[float]] = field(default_factory=dict)

    def latency_table(self) -> list[dict]:
        rows = []
        for stage, values in self.timings_ms.items():
            v = np.asarray(values)
            rows.append({"stage": stage, "p50_ms": float(np.percentile(v, 50)), "p95_ms": float(np.percentile(v, 95))})
        return rows


class BagPairs:
    """``(cloud, detections, bag_time_ns)`` pairs of a bag, paired exactly as the nodes pair them.

    After iteration, :attr:`stats` holds the pairer's counters, with the messages left
    unmatched at the end of the bag added to the drop counts.
    """

    def __init__(
        self, bag: str | Path, points_topic: str = "/points", detections_topic: str = "/detections",
        slop_s: float = 0.05,
    ) -> None:
        from pcc_ros.runtime.pairing import StampPairer, SyncStats

        self.bag, self.points_topic, self.detections_topic = Path(bag), points_topic, detections_topic
        # Bags are in time order, so a partner arrives within a few messages; a bounded queue
        # keeps pairing linear even for a bag whose streams never pair.
        self.pairer: StampPairer = StampPairer(slop_ns=int(slop_s * 1e9), queue_size=100)
        self.stats: SyncStats = self.pairer.stats
        self.undecodable = 0
        self.first_problem = ""

    def __iter__(self) -> Iterator[tuple[object, object, int]]:
        from pcc_ros.data.bag import DETECTION3DARRAY, POINTCLOUD2, check_topic_types, decode, iter_messages, open_bag
        from pcc_ros.msg.stamps import stamp_to_ns

        reader = open_bag(self.bag)
        try:
            wanted = (self.points_topic, self.detections_topic)
            expected = {self.points_topic: POINTCLOUD2, self.detections_topic: DETECTION3DARRAY}
            check_topic_types(reader, self.bag, expected, required=wanted)
            connections = [c for c in reader.connections if c.topic in wanted]
            for connection, time_ns, raw in iter_messages(reader, self.bag, connections):
                try:
                    msg = decode(reader, raw, connection, time_ns, self.bag)
                    stamp = stamp_to_ns(msg.header.stamp)
                except (PccError, AttributeError) as exc:
                    self.undecodable += 1
                    self.first_problem = self.first_problem or str(exc)
                    log.warning("skipped: %s", exc)
                    continue
                is_cloud = connection.topic == self.points_topic
                add = self.pairer.add_left if is_cloud else self.pairer.add_right
                pair = add(stamp, msg)
                if pair is not None:
                    yield pair[0], pair[1], time_ns
            left, right = self.pairer.pending()
            self.stats.dropped_clouds += left
            self.stats.dropped_detections += right
        finally:
            reader.close()


#: Types of the input topics ``pcc replay`` copies into its output.
COPIED_TOPICS = {
    "/ground_truth": "vision_msgs/msg/Detection3DArray",
    "/tf": "tf2_msgs/msg/TFMessage",
    "/tf_static": "tf2_msgs/msg/TFMessage",
}


def copy_topics(bag: str | Path, writer, topics: dict[str, str]) -> int:
    """Copy the raw records of ``topics`` (name -> expected type) from ``bag`` into an open
    :class:`BagWriter`; messages that do not deserialize are left out. Returns how many were."""
    from pcc_ros.data.bag import check_topic_types, decode, iter_messages, open_bag
    from pcc_ros.data.bag_writer import TF_STATIC_QOS

    reader = open_bag(bag)
    left_out = 0
    try:
        check_topic_types(reader, bag, topics)
        connections = [c for c in reader.connections if c.topic in topics]
        for connection, time_ns, raw in iter_messages(reader, bag, connections):
            try:
                decode(reader, raw, connection, time_ns, bag)
            except PccError:
                left_out += 1  # BagPairs logs the paired topics; the others are logged here
                if connection.topic not in ("/points", "/detections"):
                    log.warning("%s: left out an undecodable %s message at %d", bag, connection.topic, time_ns)
                continue
            qos = TF_STATIC_QOS if connection.topic == "/tf_static" else None
            writer.write_raw(connection.topic, connection.msgtype, raw, time_ns, qos)
    finally:
        reader.close()
    return left_out


def replay_bag(
    bag: str | Path,
    out: str | Path | None,
    pipeline,
    with_filter: bool = True,
    points_topic: str = "/points",
    detections_topic: str = "/detections",
    slop_s: float = 0.05,
    storage: str = "mcap",
    force: bool = False,
    copy_inputs: bool = True,
    on_result: Callable | None = None,
    progress: bool = True,
) -> ReplaySummary:
    """Replay ``bag`` through ``pipeline``; write the node outputs to ``out`` (None: don't write).

    ``on_result(result, cloud_msg, detections_msg)`` is called for each processed frame
    (the demo and evaluation use it). A frame the pipeline refuses (malformed message)
    is logged, counted and skipped, as a node would.
    """
    from contextlib import nullcontext

    from pcc_ros.data.bag_writer import atomic_bag
    from pcc_ros.pipeline.core import build_outputs

    summary = ReplaySummary()
    topics = dict(COMPLETION_TOPICS)
    if with_filter:
        topics.update(FILTER_TOPICS)
    context = atomic_bag(out, storage=storage, force=force) if out is not None else nullcontext(None)
    with context as writer:
        if writer is not None and copy_inputs:
            from pcc_ros.data.bag import DETECTION3DARRAY, POINTCLOUD2

            copied = {points_topic: POINTCLOUD2, detections_topic: DETECTION3DARRAY, **COPIED_TOPICS}
            copy_topics(bag, writer, copied)
        pairs = BagPairs(bag, points_topic, detections_topic, slop_s)
        for cloud, detections, time_ns in tqdm(pairs, unit="frame", desc="replay", disable=not progress):
            try:
                result, originals = pipeline.process_messages(cloud, detections)
            except PccError as exc:
                summary.skipped_frames += 1
                summary.first_skip_reason = summary.first_skip_reason or str(exc)
                log.warning("frame at %d skipped: %s", time_ns, exc)
                continue
            outputs = build_outputs(result, originals, detections_header=cloud.header)
            if writer is not None:
                for topic, msgtype in topics.items():
                    writer.write(topic, msgtype, outputs[topic.lstrip("/")], time_ns)
            summary.frames += 1
            summary.kept += int(result.keep.sum())
            summary.rejected += int((~result.keep).sum())
            for stage, ms in result.timings_ms.items():
                summary.timings_ms.setdefault(stage, []).append(ms)
            if on_result is not None:
                on_result(result, cloud, detections)
        summary.unpaired_clouds = pairs.stats.dropped_clouds
        summary.unpaired_detections = pairs.stats.dropped_detections
        summary.undecodable = pairs.undecodable
        if summary.frames == 0 and out is not None:  # inside the block: the output is not committed
            raise DataError(_no_frame_reason(bag, summary, slop_s, pairs.first_problem),
                            hint="nothing was written; `pcc info` shows the bag's topics, counts and damage")
    return summary


def _no_frame_reason(bag, summary: ReplaySummary, slop_s: float, first_problem: str) -> str:
    """Why no frame came out: every frame malformed, every message undecodable, or no pairing."""
    if summary.skipped_frames:
        return (f"{bag}: all {summary.skipped_frames} paired frames were malformed and skipped "
                f"(first: {summary.first_skip_reason})")
    if summary.undecodable:
        return f"{bag}: {summary.undecodable} undecodable messages left nothing to pair (first: {first_problem})"
    return (f"{bag}: no scan could be paired with detections within {slop_s} s "
            f"({summary.unpaired_clouds} clouds, {summary.unpaired_detections} detection arrays unpaired; "
            "check the stamps, or raise sync_slop in the config)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("bag", type=Path, help="input rosbag2 (MCAP or sqlite3)")
    parser.add_argument("--out", type=Path, required=True, help="output bag")
    parser.add_argument("--config", type=Path, help="node parameter YAML (default: the shipped config/*.yaml)")
    parser.add_argument("--backend", help="override the config's backend")
    parser.add_argument("--checkpoint", help="override the config's checkpoint")
    parser.add_argument("--device", help="auto | cpu | cuda | cuda:N")
    parser.add_argument(
        "--score-mapping", choices=("identity", "sigmoid"),
        help="override the config's score_mapping (sigmoid for logits, e.g. PointRCNN)",
    )
    parser.add_argument("--filter", action="store_true", help="also record the detection filter's outputs")
    parser.add_argument("--points-topic", default="/points")
    parser.add_argument("--detections-topic", default="/detections", help="e.g. /ground_truth to complete GT boxes")
    parser.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap")
    parser.add_argument("--no-copy-inputs", action="store_true", help="write only the pipeline outputs")
    parser.add_argument("--force", action="store_true", help="replace an existing output bag")


def load_config(config: Path | None, with_filter: bool, **overrides):
    """PipelineConfig from a YAML file (default: the package's shipped config) plus overrides.

    Every value goes through the nodes' own parameter check, so a file a node would refuse
    (unknown key, wrong type, value out of range) is refused here with the same message.
    """
    from pcc_ros.errors import ConfigError
    from pcc_ros.pipeline.core import read_parameters
    from pcc_ros.runtime.node import node_parameters, pipeline_config

    if config is None:
        name = "detection_filter.yaml" if with_filter else "completion.yaml"
        config = shipped_config_dir() / name
    values = read_parameters(config)
    values.update({k: v for k, v in overrides.items() if v is not None})
    try:
        values = node_parameters(values)
        return pipeline_config(values), float(values["sync_slop"])
    except ConfigError as exc:
        raise ConfigError(f"{config}: {exc}") from exc


def shipped_config_dir() -> Path:
    """``config/`` of a source checkout, or ``share/pcc_ros/config`` of an install."""
    from pcc_ros.paths import resource_dir

    folder = resource_dir("config")
    if folder is None:
        raise DataError("cannot find the shipped config/ folder; pass --config")
    return folder


def run(args: argparse.Namespace) -> int:
    from pcc_ros.pipeline.core import Pipeline
    from pcc_ros.tables import print_table

    config, slop = load_config(
        args.config, args.filter, backend=args.backend, checkpoint=args.checkpoint, device=args.device,
        score_mapping=args.score_mapping,
    )
    pipeline = Pipeline(config)
    summary = replay_bag(
        args.bag,
        args.out,
        pipeline,
        with_filter=args.filter,
        points_topic=args.points_topic,
        detections_topic=args.detections_topic,
        slop_s=slop,
        storage=args.storage,
        force=args.force,
        copy_inputs=not args.no_copy_inputs,
    )
    print_table(f"replay timing per frame ({summary.frames} frames, backend {config.backend})", summary.latency_table())
    print(
        f"\nkept {summary.kept}, rejected {summary.rejected} detections; skipped frames {summary.skipped_frames}; "
        f"undecodable messages {summary.undecodable} (left out of the output); "
        f"unpaired clouds {summary.unpaired_clouds}, unpaired detection arrays {summary.unpaired_detections}"
    )
    print(f"wrote {args.out}")
    return 0
