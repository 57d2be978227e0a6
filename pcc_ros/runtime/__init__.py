"""Runtimes the node logic (:mod:`pcc_ros.runtime.node`) runs on: the seam and its implementations.

* :mod:`pcc_ros.runtime.base` - the seam: :class:`~pcc_ros.runtime.base.Runtime`
  (publishers, subscriptions, timers, clock, logger, transforms) and
  :class:`~pcc_ros.runtime.base.QoS` with the two profiles the nodes use.
* :mod:`pcc_ros.runtime.local` - an in-process graph (no middleware): several runtimes in
  one process exchange messages synchronously; optional simulated clock. Used by tests,
  benchmarks, ``pcc replay`` and anything that wants node behaviour offline.
* the rclpy runtime lives in :mod:`pcc_ros.nodes.ros_node` (the only place rclpy is imported):
  rclpy is the one node host.
"""
