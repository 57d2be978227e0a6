"""``pcc echo TOPIC``: print messages arriving on a ROS 2 topic (like ``ros2 topic echo``), without ROS.

The type is discovered from the publishers on the graph (DDS type name
``pkg::msg::dds_::Type_`` -> ``pkg/msg/Type``) unless ``--type`` gives it. The reader is
best-effort by default, which matches reliable and best-effort writers alike. Large
messages are summarised (clouds: size, fields, point count; detections: one line per
box); ``--count N`` exits after N messages, ``--timeout S`` after S seconds.
"""

from __future__ import annotations

import argparse
import re
import time

from pcc_ros.errors import DataError

_DDS_NAME = re.compile(r"^(\w+)::(\w+)::dds_::(\w+)_$")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("topic", help="ROS topic, e.g. /completed")
    parser.add_argument("--type", help="message type, e.g. sensor_msgs/msg/PointCloud2 (default: discovered)")
    parser.add_argument("--count", type=int, default=0, help="exit after this many messages (0: run until Ctrl-C)")
    parser.add_argument("--timeout", type=float, default=0.0, help="exit after this many seconds (0: never)")
    parser.add_argument("--reliable", action="store_true", help="reliable reader (default best-effort)")


def ros_type_name(dds_type: str) -> str | None:
    """``sensor_msgs::msg::dds_::PointCloud2_`` -> ``sensor_msgs/msg/PointCloud2`` (None if not a ROS type)."""
    match = _DDS_NAME.match(dds_type)
    return "/".join(match.groups()) if match else None


def discover_type(runtime, topic: str, timeout_s: float) -> str | None:
    """The ROS type of the first publication seen on ``topic``."""
    from cyclonedds.builtin import BuiltinDataReader, BuiltinTopicDcpsPublication

    from pcc_ros.runtime.dds import dds_topic_name

    reader = BuiltinDataReader(runtime.participant, BuiltinTopicDcpsPublication)
    wanted = dds_topic_name(topic)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        for endpoint in reader.take(N=64):
            if getattr(endpoint, "topic_name", None) == wanted:
                name = ros_type_name(endpoint.type_name)
                if name:
                    return name
        time.sleep(0.05)
    return None


def summarize(msgtype: str, msg) -> str:
    """One human-readable block per message."""
    from pcc_ros.msg.stamps import stamp_to_ns

    header = getattr(msg, "header", None)
    head = f"[{stamp_to_ns(header.stamp) / 1e9:.3f} {header.frame_id}] " if header is not None else ""
    if msgtype == "sensor_msgs/msg/PointCloud2":
        fields = ",".join(f.name for f in msg.fields)
        return f"{head}PointCloud2 {msg.width}x{msg.height} points, fields {fields}, {len(msg.data)} bytes"
    if msgtype == "vision_msgs/msg/Detection3DArray":
        lines = [f"{head}Detection3DArray {len(msg.detections)} detections"]
        for det in msg.detections:
            p, s = det.bbox.center.position, det.bbox.size
            hyp = det.results[0].hypothesis if det.results else None
            label = f"{hyp.class_id} {hyp.score:.2f}" if hyp else "-"
            lines.append(f"  id={det.id!r} {label} centre=({p.x:.2f}, {p.y:.2f}, {p.z:.2f}) "
                         f"size=({s.x:.2f}, {s.y:.2f}, {s.z:.2f})")
        return "\n".join(lines)
    if msgtype == "visualization_msgs/msg/MarkerArray":
        return f"MarkerArray {len(msg.markers)} markers"
    if msgtype == "diagnostic_msgs/msg/DiagnosticArray":
        lines = [f"{head}DiagnosticArray"]
        for status in msg.status:
            values = ", ".join(f"{kv.key}={kv.value}" for kv in status.values)
            lines.append(f"  {status.name}: level {int(status.level)} {status.message} ({values})")
        return "\n".join(lines)
    text = repr(msg)
    return head + (text if len(text) < 2000 else text[:2000] + " …")


def run(args: argparse.Namespace) -> int:
    from pcc_ros.msg.typestore import get_typestore
    from pcc_ros.runtime.base import QoS
    from pcc_ros.runtime.dds import DdsRuntime

    runtime = DdsRuntime("pcc_echo")
    try:
        msgtype = args.type or discover_type(runtime, args.topic, args.timeout or 10.0)
        if msgtype is None:
            raise DataError(f"no publisher of {args.topic} found; pass --type")
        if msgtype not in get_typestore().types:
            raise DataError(f"type {msgtype} is not in the type store")
        received = []
        runtime.create_subscription(
            args.topic, msgtype, lambda m: received.append(m), QoS(reliable=args.reliable, depth=10)
        )
        deadline = time.monotonic() + args.timeout if args.timeout else None
        printed = 0
        while (not args.count or printed < args.count) and (deadline is None or time.monotonic() < deadline):
            runtime.spin_once(0.1)
            while received and (not args.count or printed < args.count):
                print(summarize(msgtype, received.pop(0)), flush=True)
                print("---", flush=True)
                printed += 1
    except KeyboardInterrupt:
        pass
    finally:
        runtime.shutdown()
    return 0
