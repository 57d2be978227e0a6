"""``builtin_interfaces/Time`` <-> integer nanoseconds, and ``std_msgs/Header``.

pcc_ros keeps time as one ``int`` of nanoseconds (exact, orderable, what bags store);
messages carry ``(sec: int32, nanosec: uint32)``. The split follows rclpy's
``Time.to_msg``: ``nanosec`` is always in ``[0, 1e9)`` and ``sec`` takes the sign, so
``-1 ns`` is ``(sec=-1, nanosec=999999999)``.
"""

from __future__ import annotations

from pcc_ros.errors import MessageError
from pcc_ros.msg.typestore import ClassResolver, new_message

NS_PER_S = 1_000_000_000
_INT32_MIN, _INT32_MAX = -(2**31), 2**31 - 1


def stamp_to_ns(stamp) -> int:
    """Nanoseconds of a ``builtin_interfaces/Time``-like object (``sec``, ``nanosec``)."""
    try:
        sec, nanosec = int(stamp.sec), int(stamp.nanosec)
    except (AttributeError, TypeError, ValueError) as exc:
        raise MessageError(f"stamp is not a builtin_interfaces/Time ({exc})") from None
    if not 0 <= nanosec < NS_PER_S:
        raise MessageError(f"stamp nanosec {nanosec} is outside [0, 1e9)")
    return sec * NS_PER_S + nanosec


def ns_to_stamp(ns: int, classes: ClassResolver | None = None):
    """A ``builtin_interfaces/msg/Time`` of the resolved class for integer nanoseconds ``ns``."""
    sec, nanosec = divmod(int(ns), NS_PER_S)
    if not _INT32_MIN <= sec <= _INT32_MAX:
        raise MessageError(f"stamp {ns} ns does not fit builtin_interfaces/Time (int32 seconds)")
    return new_message("builtin_interfaces/msg/Time", classes, sec=sec, nanosec=nanosec)


def make_header(frame_id: str, stamp_ns: int, classes: ClassResolver | None = None):
    """A ``std_msgs/msg/Header`` with ``frame_id`` and the stamp for ``stamp_ns``."""
    return new_message("std_msgs/msg/Header", classes, stamp=ns_to_stamp(stamp_ns, classes), frame_id=str(frame_id))
