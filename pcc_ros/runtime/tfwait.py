"""Frames waiting for a transform: held for a bounded time, then released or dropped, in order.

Localisation publishes ``/tf`` a little after the scan it used, stalls for seconds now and then,
and a static mount may be latched only after the first scans. A frame whose detections (or
``output_frame``) need a transform that has not arrived is therefore neither processed in the
wrong frame nor dropped at once, nor waited on for ever: :class:`TransformWait` holds it for
``tf_timeout`` seconds (monotonic time: a paused or looped sim clock cannot stretch it) and at
most ``capacity`` frames (the oldest goes first). A held frame is released as soon as its
transforms resolve; one that still does not resolve when a newer frame does, or when its time
is up, is dropped (the caller counts it). This is tf2's ``MessageFilter`` without threads of
its own: the node's worker polls :meth:`TransformWait.release` while frames wait.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from pcc_ros.msg.stamps import stamp_to_ns
from pcc_ros.msg.tf_buffer import frame_name, same_frame

#: Frames held at most (at 20 Hz, 0.4 s of scans; each holds its cloud, ~2-4 MB).
CAPACITY = 8
#: The worker's poll period while frames wait (a lookup in a dict per held frame).
POLL_S = 0.01


@dataclass(frozen=True)
class FrameTransforms:
    """The transforms one frame needs, looked up before it is processed (``None``: not needed)."""

    detections: Any = None  # scan frame <- detections' frame, at the detections' stamp
    output: Any = None  # output_frame <- scan frame, at the scan's stamp
    output_frame: str = ""


def frame_transforms(runtime: Any, cloud, detections, output_frame: str) -> tuple[FrameTransforms | None, str]:
    """The transforms a pair needs from ``runtime`` (detections in another frame than the scan: moved
    once, after decoding; an ``output_frame``), or ``(None, "'a' -> 'b'")`` naming the first one
    unknown now."""
    # tf2 in ROS 2 refuses frame ids with a leading '/' (ROS 1 drivers, converted bags): stripped
    source, scan = str(detections.header.frame_id), str(cloud.header.frame_id)
    to_scan = to_output = None
    if source and not same_frame(source, scan):
        to_scan = runtime.lookup_transform(frame_name(scan), frame_name(source), stamp_to_ns(detections.header.stamp))
        if to_scan is None:
            return None, f"'{source}' -> '{scan}'"
    if output_frame and not same_frame(output_frame, scan):
        to_output = runtime.lookup_transform(frame_name(output_frame), frame_name(scan),
                                             stamp_to_ns(cloud.header.stamp))
        if to_output is None:
            return None, f"'{scan}' -> '{output_frame}'"
    return FrameTransforms(to_scan, to_output, output_frame), ""


@dataclass
class _Held:
    pair: tuple
    deadline_ns: int
    tries: int = 0


class TransformWait:
    """Pairs waiting for their transforms, oldest first (thread-safe: the worker releases, a
    clock jump clears from a subscription callback)."""

    def __init__(self, timeout_s: float, capacity: int = CAPACITY,
                 clock: Callable[[], int] = time.monotonic_ns) -> None:
        self.timeout_s = float(timeout_s)
        self.capacity = int(capacity)
        self._clock = clock
        self._held: list[_Held] = []
        self._lock = threading.Lock()
        #: frames that waited at least one poll and were then processed
        self.released_late = 0

    def __len__(self) -> int:
        return len(self._held)

    def add(self, pair: tuple) -> list[tuple]:
        """Hold ``pair``; returns the pairs pushed out over :attr:`capacity` (oldest first)."""
        with self._lock:
            self._held.append(_Held(pair, self._clock() + int(self.timeout_s * 1e9)))
            over = len(self._held) - self.capacity
            if over <= 0:
                return []
            out, self._held = self._held[:over], self._held[over:]
            return [h.pair for h in out]

    def release(self, resolve: Callable[[tuple], tuple[Any, str]]) -> tuple[list[tuple], list[tuple]]:
        """``(ready, dropped)``: ``ready`` = ``[(pair, transforms)]`` whose ``resolve(pair)`` gave
        transforms, in arrival order; ``dropped`` = ``[(pair, missing)]`` that did not resolve and
        either timed out or are older than a frame that resolved (their stamps' transforms will
        not arrive in order any more). ``resolve`` returns ``(transforms or None, what is missing)``."""
        with self._lock:
            held, self._held = self._held, []
        results = [resolve(h.pair) for h in held]
        last_ready = max((i for i, (found, _) in enumerate(results) if found is not None), default=-1)
        now = self._clock()
        ready, dropped, keep = [], [], []
        for i, (h, (found, missing)) in enumerate(zip(held, results)):
            if found is not None:
                ready.append((h.pair, found))
                self.released_late += h.tries > 0
            elif i < last_ready or now >= h.deadline_ns:
                dropped.append((h.pair, missing))
            else:
                h.tries += 1
                keep.append(h)
        with self._lock:
            self._held = keep + self._held  # frames added meanwhile stay behind the older ones
        return ready, dropped

    def clear(self) -> int:
        """Forget every held frame (the clock jumped back); returns how many."""
        with self._lock:
            n, self._held = len(self._held), []
            return n
