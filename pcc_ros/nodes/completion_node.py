"""``ros2 run pcc_ros completion_node``: complete every detected car and republish the completed clouds.

Topics: in ``points`` (PointCloud2, sensor-data QoS) and ``detections``
(vision_msgs/Detection3DArray); out ``completed`` (PointCloud2 x, y, z, instance) and
``completed_markers`` (MarkerArray), plus ``/diagnostics``.
Parameters: see :func:`pcc_ros.pipeline.config.parameter_table` and ``config/completion.yaml``.
"""

from __future__ import annotations

import sys

from pcc_ros.nodes.entry import node_main

NODE_NAME = "completion_node"
MODE = "completion"


def main(args: list[str] | None = None) -> int:
    return node_main(NODE_NAME, MODE, args)


def main_managed(args: list[str] | None = None) -> int:
    """``ros2 run pcc_ros completion_node_managed``: the same node as a managed (lifecycle) node."""
    return node_main(NODE_NAME, MODE, args, managed=True)


if __name__ == "__main__":
    sys.exit(main())
