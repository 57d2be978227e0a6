"""Runtimes the node logic (:mod:`pcc_ros.node_core`) runs on: the seam and its implementations.

* :mod:`pcc_ros.runtime.base` - the seam: :class:`~pcc_ros.runtime.base.Runtime`
  (publishers, subscriptions, timers, clock, logger, transforms) and
  :class:`~pcc_ros.runtime.base.QoS` with the two profiles the nodes use.
* :mod:`pcc_ros.runtime.local` - an in-process graph (no middleware): several runtimes in
  one process exchange messages synchronously; optional simulated clock. Used by tests,
  benchmarks and anything that wants node behaviour offline.
* :mod:`pcc_ros.runtime.dds` - ROS 2 wire-compatible runtime over Cyclone DDS (the
  ``cyclonedds`` PyPI package): talks to a live ROS 2 Jazzy graph without a ROS install.
  Wire types in :mod:`pcc_ros.runtime.idl`, discovery configuration in
  :mod:`pcc_ros.runtime.discovery`.
* the rclpy runtime lives in :mod:`pcc_ros.nodes.ros_node` (the only place rclpy is imported).

Nothing here imports cyclonedds at package import time, so the seam and the local runtime
work where cyclonedds is not installed.
"""
