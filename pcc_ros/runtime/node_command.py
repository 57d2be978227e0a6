"""``pcc node completion|filter``: run a pcc_ros node on rclpy or, without a ROS install, on Cyclone DDS.

Same parameters (ROS 2 YAML parameter files), same topics, same pipeline on both
transports; ``--transport auto`` takes rclpy when it is importable, else DDS. On DDS the
node follows ``ROS_DOMAIN_ID`` / ``ROS_AUTOMATIC_DISCOVERY_RANGE`` and talks to a live
ROS 2 Jazzy graph (see docs/dds.md). Stop with Ctrl-C or SIGTERM.
"""

from __future__ import annotations

import argparse
import importlib.util
import signal
import threading
from pathlib import Path

from pcc_ros.errors import ConfigError

NODES = {
    "completion": ("completion_node", "completion.yaml"),
    "filter": ("detection_filter_node", "detection_filter.yaml"),
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("mode", choices=sorted(NODES), help="which node")
    parser.add_argument("--transport", choices=("auto", "dds", "rclpy"), default="auto",
                        help="auto: rclpy when importable, else Cyclone DDS")
    parser.add_argument("--params-file", type=Path, help="ROS 2 parameter YAML (default: the shipped config)")
    parser.add_argument("--backend", help="override the backend parameter")
    parser.add_argument("--checkpoint", help="override the checkpoint parameter")
    parser.add_argument("--device", help="override the device parameter (auto | cpu | cuda)")
    parser.add_argument("--name", help="node name (default: completion_node / detection_filter_node)")
    parser.add_argument("--namespace", default="/", help="namespace of the node's relative topics")
    parser.add_argument("--remap", action="append", default=[], metavar="FROM:=TO",
                        help="topic remapping, e.g. points:=/velodyne_points (repeatable)")


def choose_transport(requested: str) -> str:
    if requested != "auto":
        return requested
    return "rclpy" if importlib.util.find_spec("rclpy") is not None else "dds"


def parse_remaps(items: list[str]) -> dict[str, str]:
    out = {}
    for item in items:
        source, sep, target = item.partition(":=")
        if not sep or not source or not target:
            raise ConfigError(f"--remap {item!r}: expected FROM:=TO")
        out[source.lstrip("/")] = target
    return out


def load_parameters(args: argparse.Namespace, node_name: str) -> dict:
    from pcc_ros.bags.replay import shipped_config_dir
    from pcc_ros.pipeline import read_parameters

    path = args.params_file or shipped_config_dir() / NODES[args.mode][1]
    try:
        values = read_parameters(path, node_name)
    except ConfigError:
        values = read_parameters(path)  # a file written for another node name: its first block
    overrides = {"backend": args.backend, "checkpoint": args.checkpoint, "device": args.device}
    values.update({k: v for k, v in overrides.items() if v is not None})
    return values


def run(args: argparse.Namespace) -> int:
    default_name, _ = NODES[args.mode]
    node_name = args.name or default_name
    transport = choose_transport(args.transport)
    if transport == "rclpy":
        return _run_rclpy(args, node_name)
    return run_dds(args.mode, node_name, load_parameters(args, node_name), args.namespace, parse_remaps(args.remap))


def _run_rclpy(args: argparse.Namespace, node_name: str) -> int:
    from pcc_ros.nodes.ros_node import run as ros_run

    ros_args = ["--ros-args", "-r", f"__node:={node_name}", "-r", f"__ns:={args.namespace}"]
    if args.params_file:
        ros_args += ["--params-file", str(args.params_file)]
    for key in ("backend", "checkpoint", "device"):
        if getattr(args, key) is not None:
            ros_args += ["-p", f"{key}:={getattr(args, key)}"]
    for item in args.remap:
        ros_args += ["-r", item]
    return ros_run(node_name, args.mode, ["pcc", *ros_args])


def run_dds(mode: str, node_name: str, parameters: dict, namespace: str = "/", remap: dict | None = None,
            stop: threading.Event | None = None) -> int:
    """Host the node on the DDS runtime until ``stop`` is set, SIGINT or SIGTERM."""
    from pcc_ros.node_core import NodeCore
    from pcc_ros.runtime.dds import DdsRuntime

    stop = stop or threading.Event()
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: stop.set())
    runtime = DdsRuntime(node_name, namespace)
    core = None
    try:
        core = NodeCore(runtime, node_name, mode, parameters, remap=remap)
        runtime.start()
        d = runtime.discovery
        core.log.info(f"on DDS domain {d.domain_id} (discovery {d.range}); Ctrl-C to stop")
        stop.wait()
    finally:
        if core is not None:
            core.shutdown()
        runtime.shutdown()
    return 0
