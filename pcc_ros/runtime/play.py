"""``pcc play BAG``: publish a bag's topics onto the ROS 2 graph with their recorded timing (like ``ros2 bag play``).

Runs on the Cyclone DDS runtime, so no ROS install is needed. Every topic whose type
the type store knows is published (``/points`` best-effort keep-last 5 like a driver,
``/tf_static`` transient-local, everything else reliable keep-last 10); messages keep
their recorded spacing divided by ``--rate``. ``--wait-subscribers N`` holds the start
until every published topic has N matched readers (scripts and tests use it so no frame
is published into the void).
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

from pcc_ros.errors import DataError

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("bag", type=Path, help="rosbag2 (MCAP or sqlite3)")
    parser.add_argument("--rate", type=float, default=1.0, help="playback speed factor (default 1.0)")
    parser.add_argument("--loop", action="store_true", help="play again from the start at the end")
    parser.add_argument("--topics", nargs="+", help="only these topics (default: all)")
    parser.add_argument("--wait-subscribers", type=int, default=0, metavar="N",
                        help="before playing, wait until every topic in --wait-topics has N matched readers")
    parser.add_argument("--wait-topics", nargs="+", help="topics --wait-subscribers applies to (default: all)")
    parser.add_argument("--wait-timeout", type=float, default=30.0, help="seconds to wait for subscribers")


def topic_qos(topic: str, msgtype: str):
    from pcc_ros.runtime.base import RELIABLE, SENSOR_DATA, QoS

    if topic == "/tf_static":
        return QoS(reliable=True, depth=1, transient_local=True)
    return SENSOR_DATA if msgtype == "sensor_msgs/msg/PointCloud2" else RELIABLE


def run(args: argparse.Namespace) -> int:
    from rosbags.highlevel import AnyReader

    from pcc_ros.msg.typestore import get_typestore
    from pcc_ros.runtime.dds import DdsRuntime, wait_for

    if args.rate <= 0:
        raise DataError("--rate must be > 0")
    runtime = DdsRuntime("pcc_play")
    counts: dict[str, int] = {}
    try:
        with AnyReader([args.bag], default_typestore=get_typestore()) as reader:
            known = get_typestore().types
            connections = [c for c in reader.connections if args.topics is None or c.topic in args.topics]
            publishers = {}
            for c in connections:
                if c.msgtype not in known:
                    log.warning("%s (%s): type unknown to the type store, not played", c.topic, c.msgtype)
                    continue
                if c.topic not in publishers:
                    publishers[c.topic] = runtime.create_publisher(c.topic, c.msgtype, topic_qos(c.topic, c.msgtype))
            if not publishers:
                raise DataError(f"{args.bag}: nothing to play")
            if args.wait_subscribers > 0:
                waited = [publishers[t] for t in (args.wait_topics or publishers) if t in publishers]
                if not wait_for(lambda: all(p.matched() >= args.wait_subscribers for p in waited), args.wait_timeout):
                    counts = {p.topic_name: p.matched() for p in waited}
                    raise DataError(f"subscribers did not appear within {args.wait_timeout} s: {counts}")
            wanted = [c for c in connections if c.topic in publishers]
            counts.update(dict.fromkeys(publishers, 0))
            while True:
                start_wall, start_bag = None, None
                for connection, time_ns, raw in reader.messages(connections=wanted):
                    msg = reader.deserialize(raw, connection.msgtype)
                    if start_wall is None:
                        start_wall, start_bag = time.monotonic(), time_ns
                    delay = start_wall + (time_ns - start_bag) / 1e9 / args.rate - time.monotonic()
                    if delay > 0:
                        time.sleep(delay)
                    publishers[connection.topic].publish(msg)
                    counts[connection.topic] += 1
                if not args.loop:
                    break
            # Give reliable writers a moment to deliver the tail before the participant goes.
            time.sleep(0.5)
    except KeyboardInterrupt:
        pass
    finally:
        runtime.shutdown()
    for topic, n in sorted(counts.items()):
        print(f"{topic}: {n} messages")
    return 0
