"""``pcc replay``: the node core itself over a bag — what a live node would publish, recorded.

The bag's messages are published, in bag order and on the bag's clock, into an in-process
graph (:mod:`pcc_ros.runtime.local`, simulated time) where one
:class:`~pcc_ros.runtime.node.NodeCore` runs with ``threaded=False`` (offline nothing is
dropped for lack of time). So replay pairs with the node's own pairer and parameters
(``sync_slop``, ``queue_size``), publishes the node's topic table
(:data:`pcc_ros.runtime.node.OUTPUTS`; ``--filter`` records the completion outputs as well),
and takes the node's one tf path: the bag's ``/tf`` and ``/tf_static`` are loaded into the
graph's :class:`~pcc_ros.msg.tf_buffer.TransformBuffer`, so detections in another frame
than the scan are moved as tf2 moves them for a live node.

Failures: the output bag is written next to ``--out`` and renamed into place only after
every check passed (at least one frame processed); a message that does not deserialize is
skipped, counted and left out of the output (also of the copied input topics); a frame
the pipeline refuses, or one whose transform is unknown, is skipped and counted, as a node
would.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from contextlib import nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from pcc_ros.data.bag import (
    DETECTION3DARRAY,
    POINTCLOUD2,
    TFMESSAGE,
    check_topic_types,
    decode,
    iter_messages,
    open_bag,
)
from pcc_ros.data.bag_writer import TF_STATIC_QOS, TF_STATIC_TOPIC, TF_TOPIC, atomic_bag, check_output_bag
from pcc_ros.errors import ConfigError, DataError, PccError
from pcc_ros.msg.stamps import stamp_to_ns
from pcc_ros.pipeline.config import NODE_DEFAULTS, NODE_NAMES, load_parameters, node_parameters, pipeline_config
from pcc_ros.pipeline.core import Pipeline
from pcc_ros.runtime.base import RELIABLE, SENSOR_DATA
from pcc_ros.runtime.local import LocalGraph, LocalRuntime, resolve_topic
from pcc_ros.runtime.node import NodeCore, output_names, pipeline_stages

log = logging.getLogger(__name__)

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

    def add(self, result) -> None:
        """Count one published frame."""
        self.frames += 1
        self.kept += int(result.keep.sum())
        self.rejected += int((~result.keep).sum())
        for stage, ms in result.timings_ms.items():
            self.timings_ms.setdefault(stage, []).append(ms)


#: Types of the input topics ``pcc replay`` copies into its output (besides the paired two).
COPIED_TOPICS = {
    "/ground_truth": "vision_msgs/msg/Detection3DArray",
    TF_TOPIC: TFMESSAGE,
    TF_STATIC_TOPIC: TFMESSAGE,
}


def load_transforms(graph: LocalGraph, reader, bag: str | Path) -> int:
    """Every transform of the open bag's ``/tf`` and ``/tf_static`` into ``graph.transforms``
    (undecodable messages skipped and logged); returns how many were loaded. The topics' types
    are the caller's to check (:func:`replay_bag` checks them with the rest)."""
    loaded = 0
    connections = [c for c in reader.connections if c.topic in (TF_TOPIC, TF_STATIC_TOPIC)]
    for connection, time_ns, raw in iter_messages(reader, bag, connections):
        try:
            msg = decode(reader, raw, connection, time_ns, bag)
            loaded += graph.transforms.add_message(msg, static=connection.topic == TF_STATIC_TOPIC)
        except (PccError, AttributeError) as exc:
            log.warning("%s: a %s message left out of the transforms: %s", bag, connection.topic, exc)
    return loaded


def replay_bag(
    bag: str | Path,
    out: str | Path | None,
    pipeline: Pipeline | None = None,
    with_filter: bool = True,
    points_topic: str = "/points",
    detections_topic: str = "/detections",
    storage: str = "mcap",
    force: bool = False,
    copy_inputs: bool = True,
    on_result: Callable | None = None,
    progress: bool = True,
    parameters: dict[str, Any] | None = None,
) -> ReplaySummary:
    """Run the node core over ``bag``; write what it publishes to ``out`` (None: don't write).

    The node is built from ``parameters`` (node parameters, e.g. :func:`load_parameters`: pairing
    and queues, ``sync_slop`` among them), else from ``pipeline``'s config with the node-only
    parameters at their defaults; a given ``pipeline`` is used as it is (its loaded backend).
    ``with_filter`` runs the filter node and records the completion outputs as well.
    ``on_result(result, cloud_msg, detections_msg)`` is called for each published frame (the
    demo and evaluation use it). A frame the node refuses (malformed message, unknown
    transform) is logged, counted and skipped. The bag is opened once: its topics are checked,
    its transforms loaded, then its messages played.
    """
    if out is not None:  # a wrong --out is said before the backend loads
        check_output_bag(out, force)
    if parameters is None:
        if pipeline is None:
            raise ConfigError("replay_bag needs a pipeline or node parameters")
        parameters = {**pipeline.config.as_parameters(), **NODE_DEFAULTS}
    mode = "filter" if with_filter else "completion"
    if pipeline is None:  # the backend loads first: a bad checkpoint is named before the bag is read
        stages = pipeline_stages(output_names(mode, with_completion=with_filter))  # the live node's stages
        pipeline = Pipeline(pipeline_config(node_parameters(parameters)), **stages)
    summary = ReplaySummary()
    with open_bag(bag) as reader:
        paired = {points_topic: POINTCLOUD2, detections_topic: DETECTION3DARRAY}
        # a missing topic, or one of another type (/tf too), is named before anything is written
        check_topic_types(reader, bag, {**paired, **COPIED_TOPICS}, required=paired)
        start_ns = reader.start_time
        graph = LocalGraph(simulated=True)
        graph.advance_to(start_ns)  # before any timer exists: the clock starts at the bag's first message
        load_transforms(graph, reader, bag)

        def record(result, cloud, detections) -> None:
            summary.add(result)
            if on_result is not None:
                on_result(result, cloud, detections)

        core = NodeCore(
            LocalRuntime(graph, NODE_NAMES[mode]), NODE_NAMES[mode], mode, parameters, pipeline=pipeline,
            threaded=False, remap={"points": points_topic, "detections": detections_topic},
            outputs=output_names(mode, with_completion=with_filter), on_result=record,
        )
        player = LocalRuntime(graph, "pcc_replay")
        publishers = {
            points_topic: player.create_publisher(points_topic, POINTCLOUD2, RELIABLE),
            detections_topic: player.create_publisher(detections_topic, DETECTION3DARRAY, RELIABLE),
        }
        now = {"bag_ns": start_ns}
        context = atomic_bag(out, storage=storage, force=force) if out is not None else nullcontext(None)
        with context as writer:
            if writer is not None:  # the node's outputs, at the bag time of the message that completed the pair
                def recorder(topic: str, msgtype: str):
                    return lambda msg: writer.write(topic, msgtype, msg, now["bag_ns"])

                for name, msgtype in core.outputs.items():
                    topic = resolve_topic(core.topics[name])
                    player.create_subscription(topic, msgtype, recorder(topic, msgtype), SENSOR_DATA)
            copied = set(COPIED_TOPICS) if writer is not None and copy_inputs else set()
            first_problem = ""
            wanted = set(publishers) | copied
            connections = [c for c in reader.connections if c.topic in wanted]
            total = sum(c.msgcount for c in connections)
            messages = iter_messages(reader, bag, connections)
            for connection, time_ns, raw in tqdm(messages, total=total, unit="msg", desc="replay",
                                                 disable=not progress):
                topic = connection.topic
                try:
                    msg = decode(reader, raw, connection, time_ns, bag)
                    if topic in publishers:
                        stamp_to_ns(msg.header.stamp)  # a message without a usable stamp never pairs
                except (PccError, AttributeError) as exc:
                    if topic in publishers:
                        summary.undecodable += 1
                        first_problem = first_problem or str(exc)
                    log.warning("skipped: %s", exc)
                    continue
                if writer is not None and (topic in copied or (copy_inputs and topic in publishers)):
                    writer.write_raw(topic, connection.msgtype, raw, time_ns,
                                     TF_STATIC_QOS if topic == TF_STATIC_TOPIC else None)
                if topic in publishers:
                    now["bag_ns"] = time_ns
                    graph.advance_to(time_ns)
                    publishers[topic].publish(msg)
            stats = core.pairer.stats
            left, right = core.pairer.pending()  # never paired before the bag ended
            summary.unpaired_clouds = stats.dropped_clouds + left
            summary.unpaired_detections = stats.dropped_detections + right
            summary.skipped_frames = core.failures
            summary.first_skip_reason = core.first_failure
            core.shutdown()
            if summary.frames == 0 and out is not None:  # inside the block: the output is not committed
                raise DataError(_no_frame_reason(bag, summary, float(core.parameters["sync_slop"]), first_problem),
                                hint="nothing was written; `pcc info` shows the bag's topics, counts and damage")
    return summary


def _no_frame_reason(bag, summary: ReplaySummary, slop_s: float, first_problem: str) -> str:
    """Why no frame came out: every frame malformed, every message undecodable, or no pairing."""
    if summary.skipped_frames:
        return (f"{bag}: all {summary.skipped_frames} paired frames were skipped (malformed, or no transform) "
                f"(first: {summary.first_skip_reason})")
    if summary.undecodable:
        return f"{bag}: {summary.undecodable} undecodable messages left nothing to pair (first: {first_problem})"
    return (f"{bag}: no scan could be paired with detections within {slop_s} s "
            f"({summary.unpaired_clouds} clouds, {summary.unpaired_detections} detection arrays unpaired; "
            "check the stamps, or raise sync_slop in the config)")


@dataclass
class ReplayConfig:
    """What ``pcc replay`` is told (the CLI builds it from its flags)."""

    bag: Path
    out: Path | None
    config: Path | None = None  # node parameter YAML; None: the shipped one of the mode
    backend: str | None = None  # overrides of the file's values (None: the file's)
    checkpoint: str | None = None
    device: str | None = None
    score_mapping: str | None = None
    with_filter: bool = False  # the filter node (its outputs and the completion outputs)
    points_topic: str = "/points"
    detections_topic: str = "/detections"
    storage: str = "mcap"
    copy_inputs: bool = True
    force: bool = False
    progress: bool = True


def replay(opts: ReplayConfig, on_result: Callable | None = None) -> tuple[ReplaySummary, dict[str, Any]]:
    """Replay as ``opts`` says; returns the summary and the node parameters it ran with."""
    parameters = load_parameters(
        opts.config, opts.with_filter, backend=opts.backend, checkpoint=opts.checkpoint, device=opts.device,
        score_mapping=opts.score_mapping,
    )
    summary = replay_bag(
        opts.bag, opts.out, parameters=parameters, with_filter=opts.with_filter, points_topic=opts.points_topic,
        detections_topic=opts.detections_topic, storage=opts.storage, force=opts.force,
        copy_inputs=opts.copy_inputs, on_result=on_result, progress=opts.progress,
    )
    return summary, parameters
