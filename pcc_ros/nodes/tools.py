"""What ``pcc play`` and ``pcc echo`` share: rclpy on demand, graph waits, QoS per topic."""

from __future__ import annotations

import time
from collections.abc import Callable

from pcc_ros.errors import ConfigError


def import_rclpy(command: str):
    """``rclpy``, or a :class:`ConfigError` that says how to get it (never a bare ImportError)."""
    try:
        import rclpy
    except ImportError as exc:
        raise ConfigError(
            f"pcc {command} needs rclpy (ROS 2 Jazzy): run `make setup` (installs the ROS 2 Jazzy wheels "
            f"into the venv) or source a ROS 2 Jazzy install ({exc})"
        ) from None
    return rclpy


def wait_for(predicate: Callable[[], bool], timeout_s: float, period_s: float = 0.05) -> bool:
    """Poll ``predicate`` until it holds or ``timeout_s`` passes; its last value."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(period_s)
    return predicate()


def topic_qos(topic: str, msgtype: str):
    """What a recorder of the original graph would offer: scans best-effort keep-last 5 (a
    driver's sensor-data QoS), ``/tf_static`` transient-local, everything else reliable keep-last 10."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data

    if topic == "/tf_static":
        return QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    if msgtype == "sensor_msgs/msg/PointCloud2":
        return qos_profile_sensor_data
    return QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
