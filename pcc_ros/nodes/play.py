"""``pcc play BAG``: publish a bag's topics on the ROS 2 graph with their recorded timing (like ``ros2 bag play``).

A thin rclpy tool for users without ros2cli (the ROS 2 Jazzy wheels have none). Every topic
whose type rclpy can import is published as recorded — the bag's CDR bytes go out as they
are, nothing is decoded — with the QoS a recorder of the original graph would offer
(``/points`` best-effort keep-last 5 like a driver, ``/tf_static`` transient-local, the
rest reliable keep-last 10); messages keep their recorded spacing divided by ``--rate``.
``--clock`` also publishes ``/clock`` at each message's bag time (``use_sim_time`` nodes).
``--wait-subscribers N`` holds the start until every published topic (or those in
``--wait-topics``) has N matched readers, and ``--delay`` a little longer (a writer matches
before its readers do), so no frame is published into the void.
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

from pcc_ros.data.bag import decode, iter_messages, open_bag
from pcc_ros.errors import DataError
from pcc_ros.nodes.tools import import_rclpy, topic_qos, wait_for

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("bag", type=Path, help="rosbag2 (MCAP or sqlite3)")
    parser.add_argument("--rate", type=float, default=1.0, help="playback speed factor (default 1.0)")
    parser.add_argument("--loop", action="store_true", help="play again from the start at the end")
    parser.add_argument("--clock", action="store_true",
                        help="also publish /clock at the bag's time (nodes with use_sim_time follow it; with --loop "
                             "it jumps back at each new loop, as ros2 bag play --clock --loop)")
    parser.add_argument("--topics", nargs="+", help="only these topics (default: all)")
    parser.add_argument("--wait-subscribers", type=int, default=0, metavar="N",
                        help="before playing, wait until every topic in --wait-topics has N matched readers")
    parser.add_argument("--wait-topics", nargs="+", help="topics --wait-subscribers applies to (default: all)")
    parser.add_argument("--wait-timeout", type=float, default=30.0, help="seconds to wait for subscribers")
    parser.add_argument("--delay", type=float, default=0.0,
                        help="seconds to wait before the first message (after --wait-subscribers): lets the "
                             "readers' side of discovery finish, so best-effort topics lose no first frame")


def run(args: argparse.Namespace) -> int:
    rclpy = import_rclpy("play")
    if args.rate <= 0:
        raise DataError("--rate must be > 0")
    from rclpy.executors import ExternalShutdownException

    from pcc_ros.nodes.ros_node import rclpy_classes

    rclpy.init()
    node = rclpy.create_node("pcc_play")
    counts: dict[str, int] = {}
    undecodable: dict[str, int] = {}
    try:
        with open_bag(args.bag) as reader:
            connections = [c for c in reader.connections if args.topics is None or c.topic in args.topics]
            publishers = {}
            for c in connections:
                if c.topic in publishers:
                    continue
                try:
                    cls = rclpy_classes(c.msgtype)
                except (ImportError, AttributeError, ValueError):
                    log.warning("%s (%s): no rclpy type support for this type here, not played", c.topic, c.msgtype)
                    continue
                publishers[c.topic] = node.create_publisher(cls, c.topic, topic_qos(c.topic, c.msgtype))
            if not publishers:
                raise DataError(f"{args.bag}: nothing to play")
            if args.wait_subscribers > 0:
                waited = [publishers[t] for t in (args.wait_topics or publishers) if t in publishers]
                if not wait_for(lambda: all(p.get_subscription_count() >= args.wait_subscribers for p in waited),
                                args.wait_timeout):
                    found = {p.topic_name: p.get_subscription_count() for p in waited}
                    raise DataError(f"subscribers did not appear within {args.wait_timeout} s: {found}")
            time.sleep(max(0.0, args.delay))
            wanted = [c for c in connections if c.topic in publishers]
            counts.update(dict.fromkeys(publishers, 0))
            clock = None
            if args.clock:
                clock_class = rclpy_classes("rosgraph_msgs/msg/Clock")
                clock = node.create_publisher(clock_class, "/clock", 10)
            while True:
                start_wall, start_bag = None, None
                for connection, time_ns, raw in iter_messages(reader, args.bag, wanted):
                    try:  # a message the nodes could not decode is not put on the graph
                        decode(reader, raw, connection, time_ns, args.bag)
                    except DataError as exc:
                        if not undecodable:
                            log.warning("%s (skipped; later ones only counted)", exc)
                        undecodable[connection.topic] = undecodable.get(connection.topic, 0) + 1
                        continue
                    if start_wall is None:
                        start_wall, start_bag = time.monotonic(), time_ns
                    delay = start_wall + (time_ns - start_bag) / 1e9 / args.rate - time.monotonic()
                    if delay > 0:
                        time.sleep(delay)
                    if clock is not None:  # the bag's time first, then its message (use_sim_time nodes)
                        tick = clock_class()
                        tick.clock.sec, tick.clock.nanosec = divmod(int(time_ns), 1_000_000_000)
                        clock.publish(tick)
                    publishers[connection.topic].publish(bytes(raw))  # the recorded CDR, as is
                    counts[connection.topic] += 1
                if not args.loop:
                    break
            time.sleep(0.5)  # let reliable writers deliver the tail before the participant goes
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    for topic, n in sorted(counts.items()):
        skipped = f" ({undecodable[topic]} undecodable, not played)" if topic in undecodable else ""
        print(f"{topic}: {n} messages{skipped}")
    return 0
