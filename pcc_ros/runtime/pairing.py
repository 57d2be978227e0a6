"""Pair scans with detections by stamp, with bounded queues where the newest frame wins.

Detector wrappers often restamp their output, so a cloud and its detections rarely
carry identical stamps: they are paired when their stamps differ by at most ``slop``.
Queues are bounded; when processing falls behind, the oldest unmatched messages are
dropped and counted, never silently. Pure Python so the nodes and the
tests share one implementation (message_filters' ApproximateTimeSynchronizer does the
same under rclpy, but is not available without ROS).
"""

from __future__ import annotations

import threading
from collections import deque
from dataclasses import dataclass, field
from typing import Generic, TypeVar

T = TypeVar("T")
U = TypeVar("U")


@dataclass
class SyncStats:
    """Counters a node publishes as diagnostics."""

    paired: int = 0
    dropped_clouds: int = 0
    dropped_detections: int = 0
    dropped_pairs: int = 0  # pairs overwritten before a worker took them (newest wins)
    #: the last message dropped unpaired: its stamp, whether it was a left item (a scan), and the
    #: gap (ns) to the nearest stamp the other stream sent lately (-1: none arrived yet)
    last_drop_stamp_ns: int = 0
    last_drop_left: bool = True
    last_drop_gap_ns: int = -1


@dataclass
class StampPairer(Generic[T, U]):
    """Match items of two streams whose stamps (ns) are within ``slop_ns``.

    ``add_left`` / ``add_right`` return the matched ``(left, right)`` pair, or ``None``.
    Each queue holds at most ``queue_size`` unmatched items; older ones are dropped
    once a newer pair matches (they can no longer be paired in order) or the queue is full.
    """

    slop_ns: int
    queue_size: int = 2
    stats: SyncStats = field(default_factory=SyncStats)

    def __post_init__(self) -> None:
        self._left: deque[tuple[int, T]] = deque()
        self._right: deque[tuple[int, U]] = deque()
        #: the latest arrival stamps of each stream, paired or not (why a dropped one found no partner)
        self._recent_left: deque[int] = deque(maxlen=16)
        self._recent_right: deque[int] = deque(maxlen=16)
        self._lock = threading.Lock()

    def add_left(self, stamp_ns: int, item: T) -> tuple[T, U] | None:
        with self._lock:
            return self._add(self._left, self._right, stamp_ns, item, left=True)

    def add_right(self, stamp_ns: int, item: U) -> tuple[T, U] | None:
        with self._lock:
            return self._add(self._right, self._left, stamp_ns, item, left=False)

    def pending(self) -> tuple[int, int]:
        """Unmatched (left, right) items still queued."""
        with self._lock:
            return len(self._left), len(self._right)

    def clear(self) -> None:
        """Forget every queued message and recent stamp (the clock jumped back: they belong to the old
        timeline); the counters stay."""
        with self._lock:
            self._left.clear()
            self._right.clear()
            self._recent_left.clear()
            self._recent_right.clear()

    def _add(self, own: deque, other: deque, stamp_ns: int, item, left: bool):
        (self._recent_left if left else self._recent_right).append(stamp_ns)
        best = None
        for k, (stamp, _) in enumerate(other):
            gap = abs(stamp - stamp_ns)
            if gap <= self.slop_ns and (best is None or gap < best[0]):
                best = (gap, k)
        if best is None:
            own.append((stamp_ns, item))
            while len(own) > self.queue_size:
                self._count_drop(left, own.popleft()[0])
            return None
        _, k = best
        _, other_item = other[k]
        # Everything older than the match in the other queue can never pair in order.
        for _ in range(k):
            self._count_drop(not left, other.popleft()[0])
        other.popleft()
        while own and own[0][0] <= stamp_ns:
            self._count_drop(left, own.popleft()[0])
        self.stats.paired += 1
        return (item, other_item) if left else (other_item, item)

    def _count_drop(self, left: bool, stamp_ns: int) -> None:
        recent = self._recent_right if left else self._recent_left
        self.stats.last_drop_stamp_ns, self.stats.last_drop_left = stamp_ns, left
        self.stats.last_drop_gap_ns = min((abs(s - stamp_ns) for s in recent), default=-1)
        if left:
            self.stats.dropped_clouds += 1
        else:
            self.stats.dropped_detections += 1


class LatestSlot(Generic[T]):
    """A one-element hand-off between a subscriber callback and a worker: newest wins.

    ``put`` replaces a pending item (counting it as dropped), ``take`` blocks until an
    item is there or ``timeout`` passes. This bounds latency: a slow backend processes
    the most recent frame rather than a growing backlog.
    """

    def __init__(self, stats: SyncStats | None = None) -> None:
        self.stats = stats or SyncStats()
        self._item: T | None = None
        self._cond = threading.Condition()
        self._closed = False

    def put(self, item: T) -> None:
        with self._cond:
            if self._item is not None:
                self.stats.dropped_pairs += 1
            self._item = item
            self._cond.notify()

    def take(self, timeout: float | None = None) -> T | None:
        with self._cond:
            if self._item is None and not self._closed:
                self._cond.wait(timeout)
            item, self._item = self._item, None
            return item

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()
