"""The console entry of both nodes: ``--help`` and a clear message without ROS, then rclpy.

Runs before rclpy is imported, so ``completion_node --help`` works on any machine, and a
machine without ROS 2 gets a sentence saying what is missing instead of a traceback.
"""

from __future__ import annotations

import importlib
import sys

from pcc_ros.pipeline.config import CONFIG_FILES, parameter_table
from pcc_ros.pipeline.outputs import COMPLETED_CLOUD_DTYPE
from pcc_ros.runtime.node import DIAGNOSTICS_TOPIC, INPUTS, OUTPUTS


def _topic(name: str, msg_type: str) -> str:
    """``name (Type)``; the completed cloud also names its point fields."""
    kind = msg_type.rsplit("/", 1)[-1]
    if kind == "PointCloud2" and name not in INPUTS:
        kind = " ".join([kind, *COMPLETED_CLOUD_DTYPE.names])
    return f"{name} ({kind})"


def topics(mode: str) -> str:
    """The ``--help`` lines of a node's topics, drawn from the one topic table
    (:data:`pcc_ros.runtime.node.INPUTS`, :data:`~pcc_ros.runtime.node.OUTPUTS`), so they cannot drift."""
    inputs = ", ".join(_topic(n, t) for n, t in INPUTS.items())
    outputs = ", ".join([*(_topic(n, t) for n, t in OUTPUTS[mode].items()), DIAGNOSTICS_TOPIC])
    return f"in: {inputs}\n  out: {outputs}"
#: ROS 2 message packages the nodes use (vision_msgs is not among the PyPI wheels: it is built at set-up).
MESSAGE_PACKAGES = ("sensor_msgs", "vision_msgs", "visualization_msgs", "diagnostic_msgs")


def usage(node_name: str, mode: str) -> str:
    lines = [
        f"usage: ros2 run pcc_ros {node_name}[_managed] [--ros-args --params-file FILE -p NAME:=VALUE -r FROM:=TO ...]",
        "",
        f"  {topics(mode)}",
        "",
        f"  shipped parameters: share/pcc_ros/config/{CONFIG_FILES[mode]} (source tree: config/{CONFIG_FILES[mode]})",
        "  parameters (name, type, default; docs/nodes.md has the rules and descriptions):",
    ]
    for spec in parameter_table():
        default = list(spec.default) if isinstance(spec.default, tuple) else spec.default
        flag = "  [read-only]" if spec.read_only else ""
        lines.append(f"    {spec.name:<28} {spec.type_name:<13} {default!r}{flag}")
    return "\n".join(lines)


def missing_ros_message(node_name: str, exc: ImportError) -> str:
    missing = (getattr(exc, "name", None) or str(exc)).split(".")[0]
    return (
        f"{node_name}: cannot start: the ROS 2 Python package '{missing}' is not importable ({exc}).\n"
        "The nodes run on ROS 2 Jazzy: source /opt/ros/jazzy/setup.bash (and your workspace's "
        "install/setup.bash), or install the ROS 2 wheels into this venv with `make setup` "
        "(README, 'The nodes').\n"
        "Without ROS, the same pipeline runs offline over a bag: pcc replay BAG --out OUT [--filter]."
    )


def node_main(node_name: str, mode: str, args: list[str] | None = None, managed: bool = False) -> int:
    """``main()`` of a node: ``-h``/``--help`` without ROS, a clear error when rclpy is missing.
    ``managed``: the lifecycle node (:mod:`pcc_ros.nodes.lifecycle`), which serves once configured
    and activated."""
    argv = list(sys.argv[1:] if args is None else args)
    own = argv[: argv.index("--ros-args")] if "--ros-args" in argv else argv
    if "-h" in own or "--help" in own:
        print(usage(node_name, mode))
        return 0
    try:
        for package in MESSAGE_PACKAGES:  # imported later by the node: check them before starting
            importlib.import_module(f"{package}.msg")
        from pcc_ros.nodes.ros_node import PipelineNode, run  # rclpy only from here on

        node_class = PipelineNode
        if managed:
            from pcc_ros.nodes.lifecycle import ManagedPipelineNode as node_class
    except ImportError as exc:
        print(missing_ros_message(node_name, exc), file=sys.stderr)
        return 1
    return run(node_name, mode, args, node_class)
