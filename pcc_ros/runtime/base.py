"""The runtime seam: what node logic needs from a middleware, and nothing more.

:class:`pcc_ros.runtime.node.NodeCore` only talks to a :class:`Runtime`, so the same pairing,
worker, pipeline and diagnostics run on rclpy (``ros2 run``, :mod:`pcc_ros.nodes.ros_node`)
and in-process (:mod:`pcc_ros.runtime.local`: tests, ``pcc replay``).

Message objects crossing the seam are of the runtime's own class flavour:
:attr:`Runtime.classes` resolves a type name (``"sensor_msgs/msg/PointCloud2"``) to the
class its publishers accept and its callbacks receive; every builder in
:mod:`pcc_ros.msg` takes that resolver.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

from pcc_ros.geometry.transforms import Transform


@dataclass(frozen=True)
class QoS:
    """The QoS knobs the nodes set explicitly (anything else stays at the DDS default).

    A best-effort writer never matches a reliable reader (DDS request/offer rule), which
    every runtime honours.
    """

    reliable: bool
    depth: int
    transient_local: bool = False

    def compatible_with_reader(self, reader: QoS) -> bool:
        """True when a writer with this QoS matches ``reader`` (RxO for reliability/durability)."""
        if reader.reliable and not self.reliable:
            return False
        return not (reader.transient_local and not self.transient_local)


#: Scans: best-effort, keep-last 5, volatile (rclpy's ``qos_profile_sensor_data``).
SENSOR_DATA = QoS(reliable=False, depth=5)
#: Detections and every output: reliable, keep-last 10, volatile.
RELIABLE = QoS(reliable=True, depth=10)


class Publisher(Protocol):
    def publish(self, msg: Any) -> None: ...

    def get_subscription_count(self) -> int:
        """Subscriptions matched to this publisher now (rclpy's own method of that name)."""
        ...


class Logger(Protocol):
    """The subset of rclpy's logger and :class:`logging.Logger` both offer (preformatted strings)."""

    def debug(self, msg: str) -> Any: ...
    def info(self, msg: str) -> Any: ...
    def warning(self, msg: str) -> Any: ...
    def error(self, msg: str) -> Any: ...


@runtime_checkable
class Runtime(Protocol):
    """One node's handle on a middleware."""

    #: ``"pkg/msg/Type"`` -> message class of this runtime's flavour.
    classes: Callable[[str], type]

    def create_publisher(self, topic: str, msgtype: str, qos: QoS) -> Publisher: ...

    def create_subscription(self, topic: str, msgtype: str, callback: Callable[[Any], None], qos: QoS) -> Any: ...

    def create_timer(self, period_s: float, callback: Callable[[], None]) -> Any: ...

    def now_ns(self) -> int: ...

    def get_logger(self) -> Logger: ...

    def lookup_transform(self, target: str, source: str, stamp_ns: int) -> Transform | None:
        """``source`` -> ``target`` at ``stamp_ns`` from what has arrived, without waiting; ``None``
        when unknown (the node core holds the frame for ``tf_timeout``, then drops and counts it)."""
        ...

    def on_clock_jump(self, callback: Callable[[], None]) -> None:
        """Call ``callback`` right after the node's clock jumps back (``/clock`` under ``use_sim_time``),
        before the messages of the new timeline are handed to the node."""
        ...

    def reset_transforms(self) -> None:
        """Forget the dynamic transforms (``/tf``), keep the static ones: the clock jumped back."""
        ...

    def count_publishers(self, topic: str) -> int:
        """Publishers on ``topic`` (a resolved name) now: a warning checks there is one before
        blaming QoS or the middleware."""
        ...

    def resolve_topic(self, topic: str) -> str:
        """``topic`` as the graph names it: remapped and expanded in the node's namespace."""
        ...
