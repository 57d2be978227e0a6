"""``ros2 run pcc_ros detection_filter_node``: drop detections whose shape does not match a vehicle (TraPCC).

Topics: in ``points`` (PointCloud2, sensor-data QoS) and ``detections``
(vision_msgs/Detection3DArray); out ``detections_filtered`` / ``detections_rejected``
(Detection3DArray) and ``filter_markers`` (MarkerArray), plus ``/diagnostics``.
Parameters: see :func:`pcc_ros.pipeline.config.parameter_table` and ``config/detection_filter.yaml``.
"""

from __future__ import annotations

import sys

from pcc_ros.nodes.entry import node_main

NODE_NAME = "detection_filter_node"
MODE = "filter"


def main(args: list[str] | None = None) -> int:
    return node_main(NODE_NAME, MODE, args)


def main_managed(args: list[str] | None = None) -> int:
    """``ros2 run pcc_ros detection_filter_node_managed``: the same node as a managed (lifecycle) node."""
    return node_main(NODE_NAME, MODE, args, managed=True)


if __name__ == "__main__":
    sys.exit(main())
