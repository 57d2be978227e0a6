"""``pcc echo TOPIC``: print the messages arriving on a ROS 2 topic (like ``ros2 topic echo``).

A thin rclpy tool for users without ros2cli (the ROS 2 Jazzy wheels have none). The type is
taken from the graph (the first publisher of the topic) unless ``--type`` gives it. The
reader is best-effort by default, which matches reliable and best-effort writers alike.
Large messages are summarised (clouds: size, fields, point count; detections: one line per
box; diagnostics: one line per status); ``--count N`` exits after N messages, ``--timeout
S`` after S seconds.
"""

from __future__ import annotations

import argparse
import time

from pcc_ros.errors import DataError
from pcc_ros.msg.stamps import stamp_to_ns
from pcc_ros.nodes.tools import import_rclpy, wait_for


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("topic", help="ROS topic, e.g. /completed")
    parser.add_argument("--type", help="message type, e.g. sensor_msgs/msg/PointCloud2 (default: from the graph)")
    parser.add_argument("--count", type=int, default=0, help="exit after this many messages (0: run until Ctrl-C)")
    parser.add_argument("--timeout", type=float, default=0.0, help="exit after this many seconds (0: never)")
    parser.add_argument("--reliable", action="store_true", help="reliable reader (default best-effort)")


def summarize(msgtype: str, msg) -> str:
    """One human-readable block per message (rclpy or rosbags flavour)."""
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
            level = status.level[0] if isinstance(status.level, bytes) else int(status.level)  # rclpy: bytes
            values = ", ".join(f"{kv.key}={kv.value}" for kv in status.values)
            lines.append(f"  {status.name}: level {level} {status.message} ({values})")
        return "\n".join(lines)
    text = repr(msg)
    return head + (text if len(text) < 2000 else text[:2000] + " …")


def run(args: argparse.Namespace) -> int:
    rclpy = import_rclpy("echo")
    from rclpy.executors import ExternalShutdownException
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    from pcc_ros.nodes.ros_node import rclpy_classes

    rclpy.init()
    node = rclpy.create_node("pcc_echo")
    try:
        msgtype = args.type
        if msgtype is None:
            def found() -> bool:
                return any(name == args.topic for name, _ in node.get_topic_names_and_types())

            if not wait_for(found, args.timeout or 10.0):
                raise DataError(f"no publisher of {args.topic} found; pass --type")
            msgtype = dict(node.get_topic_names_and_types())[args.topic][0]
        try:
            cls = rclpy_classes(msgtype)
        except (ImportError, AttributeError, ValueError) as exc:
            raise DataError(f"type {msgtype} cannot be imported here ({exc})") from None
        received = []
        reliability = ReliabilityPolicy.RELIABLE if args.reliable else ReliabilityPolicy.BEST_EFFORT
        node.create_subscription(cls, args.topic, received.append, QoSProfile(depth=10, reliability=reliability))
        deadline = time.monotonic() + args.timeout if args.timeout else None
        printed = 0
        while (not args.count or printed < args.count) and (deadline is None or time.monotonic() < deadline):
            rclpy.spin_once(node, timeout_sec=0.1)
            while received and (not args.count or printed < args.count):
                print(summarize(msgtype, received.pop(0)), flush=True)
                print("---", flush=True)
                printed += 1
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0
