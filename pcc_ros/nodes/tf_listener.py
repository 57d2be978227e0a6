"""tf for the rclpy host: tf2_ros where it is installed, else the package's own listener.

A ROS 2 install has tf2_ros: its ``Buffer`` and ``TransformListener`` answer. The ROS 2 Jazzy
wheels from PyPI do not ship tf2_ros, only what ``scripts/setup_ros.sh`` builds (tf2_msgs):
there :class:`pcc_ros.runtime.tf.TransformListener` subscribes to ``/tf`` and ``/tf_static``
itself and looks transforms up in :class:`pcc_ros.msg.tf_buffer.TransformBuffer`, the buffer
``pcc replay`` uses. Both are a :class:`pcc_ros.runtime.tf.TransformSource`; neither blocks
(the node core holds a frame whose transform has not arrived for ``tf_timeout``).
"""

from __future__ import annotations

import importlib.util

from rclpy.node import Node
from rclpy.time import Time

from pcc_ros.geometry.transforms import Transform
from pcc_ros.runtime.base import Runtime
from pcc_ros.runtime.tf import TransformListener, TransformSource


class Tf2RosSource:
    """tf2_ros's buffer and listener (a ROS 2 install)."""

    name = "tf2_ros"

    def __init__(self, node: Node) -> None:
        from tf2_ros import Buffer
        from tf2_ros import TransformListener as Tf2Listener

        self.buffer = Buffer()
        self.listener = Tf2Listener(self.buffer, node, spin_thread=False)  # the node's executor spins it

    def lookup(self, target: str, source: str, stamp_ns: int) -> Transform | None:
        try:  # no timeout: answered from what arrived
            tf = self.buffer.lookup_transform(target, source, Time(nanoseconds=stamp_ns))
        except Exception:  # tf2 raises several unrelated exception types (lookup, extrapolation, connectivity)
            return None
        t, q = tf.transform.translation, tf.transform.rotation
        return Transform((t.x, t.y, t.z), (q.x, q.y, q.z, q.w))

    def clear(self) -> None:
        self.buffer.clear()


def transform_source(node: Node, runtime: Runtime) -> TransformSource | None:
    """tf2_ros where installed, else the package's listener where tf2_msgs imports; None without
    either (a venv set up before tf2_msgs was built: ``make setup`` builds it)."""
    if importlib.util.find_spec("tf2_ros") is not None:
        return Tf2RosSource(node)
    if importlib.util.find_spec("tf2_msgs") is not None:
        return TransformListener(runtime)
    return None
