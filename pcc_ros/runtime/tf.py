"""``/tf`` and ``/tf_static`` into the package's :class:`~pcc_ros.msg.tf_buffer.TransformBuffer`, on any runtime.

Where tf2_ros is not installed (the ROS 2 Jazzy wheels from PyPI ship only its messages, which
``scripts/setup_ros.sh`` builds), a node still needs the transforms a tracker or a map-frame
detector implies. :class:`TransformListener` subscribes to both topics as tf2_ros's listener
does (``/tf`` reliable keep-last 100; ``/tf_static`` reliable keep-last 100 *transient local*,
so static transforms latched before the node started reach it) and answers lookups from the
same buffer ``pcc replay`` uses: one semantics (the tree walked as tf2 walks it, dynamic edges
interpolated, extrapolation refused) offline and online.

The rclpy host picks tf2_ros's own buffer where it exists (:mod:`pcc_ros.nodes.tf_listener`);
both answer through :class:`TransformSource`.
"""

from __future__ import annotations

import threading
from typing import Protocol

from pcc_ros.geometry.transforms import Transform
from pcc_ros.msg.tf_buffer import TransformBuffer
from pcc_ros.runtime.base import QoS, Runtime

TF_TOPIC = "/tf"
TF_STATIC_TOPIC = "/tf_static"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
#: tf2_ros's ``DynamicListenerQoS`` and ``StaticListenerQoS``.
TF_QOS = QoS(reliable=True, depth=100)
TF_STATIC_QOS = QoS(reliable=True, depth=100, transient_local=True)
#: tf2's default cache: dynamic samples older than this behind the newest are forgotten.
CACHE_NS = 10_000_000_000
#: The cache is trimmed once per this many ``/tf`` messages (a bisect per child frame each time).
_TRIM_EVERY = 32


class TransformSource(Protocol):
    """What the node core asks of tf: a lookup that never blocks, and a reset."""

    #: what answers (``"tf2_ros"`` or ``"pcc_ros TransformBuffer"``), for logs and diagnostics
    name: str

    def lookup(self, target: str, source: str, stamp_ns: int) -> Transform | None:
        """``target <- source`` at ``stamp_ns`` if known now, else None (no waiting: the node
        core holds the frame itself for ``tf_timeout``)."""
        ...

    def clear(self) -> None:
        """Forget the dynamic transforms (the clock jumped back); static ones stay."""
        ...


class TransformListener:
    """``/tf`` + ``/tf_static`` of ``runtime``'s graph in a :class:`TransformBuffer` (thread-safe:
    subscription callbacks add, the node's worker looks up)."""

    name = "pcc_ros TransformBuffer"

    def __init__(self, runtime: Runtime, cache_ns: int = CACHE_NS) -> None:
        self.buffer = TransformBuffer()
        self.cache_ns = int(cache_ns)
        self.messages = 0
        self._lock = threading.Lock()
        self.subscriptions = [
            runtime.create_subscription(TF_TOPIC, TF_MESSAGE, self._on_tf, TF_QOS),
            runtime.create_subscription(TF_STATIC_TOPIC, TF_MESSAGE, self._on_tf_static, TF_STATIC_QOS),
        ]

    def _on_tf(self, msg) -> None:
        with self._lock:
            self.buffer.add_message(msg, static=False)
            self.messages += 1
            if self.messages % _TRIM_EVERY == 0:  # bounded memory over hours of /tf
                newest = self.buffer.newest_stamp()
                if newest > self.cache_ns:
                    self.buffer.forget_before(newest - self.cache_ns)

    def _on_tf_static(self, msg) -> None:
        with self._lock:
            self.buffer.add_message(msg, static=True)

    def lookup(self, target: str, source: str, stamp_ns: int) -> Transform | None:
        with self._lock:
            return self.buffer.lookup(target, source, stamp_ns)

    def clear(self) -> None:
        with self._lock:
            self.buffer.clear_dynamic()
