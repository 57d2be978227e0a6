"""Start completion_node and detection_filter_node (and, with rviz:=true, RViz).

    ros2 launch pcc_ros perception.launch.py points:=/velodyne_points detections:=/detector/boxes
    ros2 launch pcc_ros perception.launch.py namespace:=/car1 backend:=mirror device:=cuda
    ros2 launch pcc_ros perception.launch.py score_mapping:=sigmoid use_sim_time:=true   # PointRCNN, bag + --clock
    ros2 launch pcc_ros perception.launch.py params_file:=/path/my_params.yaml outputs:=/perception/pcc

Arguments (``ros2 launch pcc_ros perception.launch.py --show-args`` lists them):

* ``params_file``: one YAML file with a ``/**/completion_node`` and a
  ``/**/detection_filter_node`` block; empty = the shipped ``config/completion.yaml`` and
  ``config/detection_filter.yaml``.
* ``namespace``: namespace of both nodes (relative topics resolve inside it).
* ``points`` / ``detections``: the input topics (remaps of ``points`` / ``detections``).
* ``outputs``: namespace of the output topics (``<outputs>/completed``,
  ``<outputs>/completed_markers``, ``<outputs>/detections_filtered``,
  ``<outputs>/detections_rejected``, ``<outputs>/filter_markers``); empty = the nodes' namespace.
* ``backend``, ``device``, ``score_mapping``: override the parameter file's value for both
  nodes; empty = keep the file's value.
* ``use_sim_time``: ``true`` to follow ``/clock`` (``ros2 bag play --clock``).
* ``managed``: ``true`` starts the managed (lifecycle) nodes (``completion_node_managed``,
  ``detection_filter_node_managed``): they load in ``configure`` and serve in ``activate``.
* ``autostart``: with ``managed:=true``, ``true`` (the default) configures and activates them at
  once (launch_ros' ``LifecycleNode(autostart=True)``); ``false`` leaves them unconfigured for a
  lifecycle manager (``ros2 lifecycle set /completion_node configure`` ...).
* ``rviz``: ``true`` also starts ``rviz2`` with ``config/pcc_ros.rviz``.

Every argument is plain text turned into node options by :func:`node_options` (no ROS
imports there), which the package's tests check without ROS.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch_ros.actions import LifecycleNode, Node

#: (name, default, description) of every launch argument.
ARGUMENTS = (
    ("params_file", "", "YAML with /**/completion_node and /**/detection_filter_node blocks; empty = shipped config"),
    ("namespace", "", "namespace of both nodes"),
    ("points", "points", "input sensor_msgs/PointCloud2 topic"),
    ("detections", "detections", "input vision_msgs/Detection3DArray topic"),
    ("outputs", "", "namespace of the output topics; empty = the nodes' namespace"),
    ("backend", "", "completion backend (pointpncnet, trapcc, aml, aml_ml, mirror, densify, input); "
     "empty = the params file's"),
    ("device", "", "auto, cpu, cuda or cuda:N; empty = the params file's"),
    ("score_mapping", "", "identity (probabilities) or sigmoid (logits, e.g. PointRCNN); empty = the params file's"),
    ("use_sim_time", "false", "true: use /clock (bag replay with --clock)"),
    ("managed", "false", "true: the managed (lifecycle) nodes, which load in configure and serve in activate"),
    ("autostart", "true", "with managed:=true: configure and activate at once; false: wait for a lifecycle manager"),
    ("rviz", "false", "true: also start rviz2 with config/pcc_ros.rviz"),
)
NODES = (("completion_node", "completion.yaml"), ("detection_filter_node", "detection_filter.yaml"))
OUTPUT_TOPICS = ("completed", "completed_markers", "detections_filtered", "detections_rejected", "filter_markers")


def _flag(text: str, name: str) -> bool:
    value = text.strip().lower()
    if value not in ("true", "false", "1", "0"):
        raise ValueError(f"launch argument {name}:={text!r}: use true or false")
    return value in ("true", "1")


def node_options(args: dict, share: str) -> list:
    """``(action, options)`` of every process to start (``action``: ``"Node"`` or, for a managed
    node, ``"LifecycleNode"``, the ``launch_ros.actions`` class), from the launch arguments' text."""
    namespace = args["namespace"].strip()
    managed = _flag(args["managed"], "managed")
    autostart = _flag(args["autostart"], "autostart")
    overrides = {"use_sim_time": _flag(args["use_sim_time"], "use_sim_time")}
    for name in ("backend", "device", "score_mapping"):
        if args[name].strip():
            overrides[name] = args[name].strip()
    remappings = [("points", args["points"]), ("detections", args["detections"])]
    outputs = args["outputs"].strip().rstrip("/")
    if outputs:
        remappings += [(topic, f"{outputs}/{topic}") for topic in OUTPUT_TOPICS]
    processes = []
    for name, config in NODES:
        params_file = args["params_file"].strip() or os.path.join(share, "config", config)
        options = {
            "package": "pcc_ros",
            "executable": f"{name}_managed" if managed else name,
            "name": name,
            "namespace": namespace,
            "parameters": [params_file, overrides],
            "remappings": remappings,
            "output": "screen",
        }
        if managed:
            options["autostart"] = autostart
        processes.append(("LifecycleNode" if managed else "Node", options))
    if _flag(args["rviz"], "rviz"):
        processes.append(
            (
                "Node",
                {
                    "package": "rviz2",
                    "executable": "rviz2",
                    "name": "rviz2",
                    "namespace": namespace,
                    "arguments": ["-d", os.path.join(share, "config", "pcc_ros.rviz")],
                    "parameters": [{"use_sim_time": overrides["use_sim_time"]}],
                    "output": "screen",
                },
            )
        )
    return processes


def _launch_nodes(context, *args, **kwargs):
    values = {name: context.launch_configurations.get(name, default) for name, default, _ in ARGUMENTS}
    share = get_package_share_directory("pcc_ros")
    actions = {"Node": Node, "LifecycleNode": LifecycleNode}
    return [actions[action](**options) for action, options in node_options(values, share)]


def generate_launch_description() -> LaunchDescription:
    declared = [DeclareLaunchArgument(name, default_value=value, description=text) for name, value, text in ARGUMENTS]
    return LaunchDescription([*declared, OpaqueFunction(function=_launch_nodes)])
