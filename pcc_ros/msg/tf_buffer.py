"""The transform tree of ``/tf`` and ``/tf_static``, looked up as tf2 looks it up, without ROS.

A :class:`TransformBuffer` holds every edge ``parent <- child`` it was given: static edges
(``/tf_static``: valid at any time) and dynamic ones (``/tf``: a stamped series per child).
:meth:`TransformBuffer.lookup` answers ``target <- source`` at a stamp through the tree, as
``tf2_ros.Buffer.lookup_transform`` does: both frames walk up to their common ancestor,
every dynamic edge is taken at the same stamp — its sample at that stamp, or the linear /
slerp interpolation of the two samples around it — and a stamp outside a dynamic edge's
samples is an extrapolation, answered ``None`` (stamp 0 means "the latest", as in tf2).

The in-process runtime (:mod:`pcc_ros.runtime.local`) and ``pcc replay`` (which loads a
bag's ``/tf`` and ``/tf_static`` into one) answer the node core's lookups from it, so a
replayed bag moves detections in another frame exactly as a live node's tf2 does.
"""

from __future__ import annotations

import bisect
import logging
from dataclasses import dataclass, field

import numpy as np

from pcc_ros.geometry.transforms import IDENTITY, Transform
from pcc_ros.msg.stamps import stamp_to_ns

log = logging.getLogger(__name__)

#: Longest parent chain followed (a loop in a broken tree ends here instead of hanging).
MAX_DEPTH = 64


def frame_name(frame_id: str) -> str:
    """tf2's frame name: no leading slash (``/base_link`` and ``base_link`` are one frame)."""
    return str(frame_id).lstrip("/")


def same_frame(a: str, b: str) -> bool:
    """Frame ids naming one frame: equal but for a leading '/' (ROS 1 drivers and converted
    bags write ``/velodyne``; tf2 in ROS 2 names the same frame ``velodyne``)."""
    return frame_name(a) == frame_name(b)


@dataclass
class _Series:
    """One child's dynamic edge: its parent and the samples, sorted by stamp."""

    parent: str
    stamps: list[int] = field(default_factory=list)
    transforms: list[Transform] = field(default_factory=list)

    def add(self, stamp_ns: int, transform: Transform) -> None:
        k = bisect.bisect_left(self.stamps, stamp_ns)
        if k < len(self.stamps) and self.stamps[k] == stamp_ns:
            self.transforms[k] = transform  # a re-sent sample replaces the old one
            return
        self.stamps.insert(k, stamp_ns)
        self.transforms.insert(k, transform)

    def forget_before(self, stamp_ns: int) -> None:
        """Drop the samples older than the newest one at or before ``stamp_ns``."""
        k = bisect.bisect_right(self.stamps, stamp_ns) - 1
        if k > 0:
            del self.stamps[:k], self.transforms[:k]

    def at(self, stamp_ns: int) -> Transform | None:
        if stamp_ns == 0:
            return self.transforms[-1]
        k = bisect.bisect_left(self.stamps, stamp_ns)
        if k < len(self.stamps) and self.stamps[k] == stamp_ns:
            return self.transforms[k]
        if k == 0 or k == len(self.stamps):
            return None  # extrapolation into the past or the future
        before, after = self.stamps[k - 1], self.stamps[k]
        return self.transforms[k - 1].interpolate(self.transforms[k], (stamp_ns - before) / (after - before))


class TransformBuffer:
    """Static and dynamic transforms by child frame; ``target <- source`` lookups through the tree."""

    def __init__(self) -> None:
        self._static: dict[str, tuple[str, Transform]] = {}
        self._dynamic: dict[str, _Series] = {}
        self.invalid = 0  # transforms refused (non-finite, zero rotation, a frame its own parent)

    def set_transform(self, parent: str, child: str, transform: Transform, stamp_ns: int | None = None) -> bool:
        """Add the edge ``parent <- child``: static without ``stamp_ns`` (``/tf_static``), else one
        sample of a dynamic edge (``/tf``). A transform that is not rigid is counted and refused (False)."""
        parent, child = frame_name(parent), frame_name(child)
        values = np.asarray([*transform.translation, *transform.rotation], dtype=np.float64)
        norm = float(np.linalg.norm(values[3:]))
        if not np.isfinite(values).all() or norm < 1e-9 or not parent or not child or parent == child:
            self.invalid += 1
            if self.invalid == 1:
                log.warning("refused transform %r <- %r: %s (further refusals are only counted)", parent, child,
                            values.tolist())
            return False
        rotation = tuple(float(v) for v in values[3:] / norm)
        transform = Transform(tuple(float(v) for v in values[:3]), rotation)
        if stamp_ns is None:
            self._static[child] = (parent, transform)
            return True
        series = self._dynamic.get(child)
        if series is None or series.parent != parent:  # a new parent replaces the old series (tf2 warns)
            series = self._dynamic[child] = _Series(parent)
        series.add(int(stamp_ns), transform)
        return True

    def add_message(self, msg, static: bool) -> int:
        """Every ``geometry_msgs/TransformStamped`` of a ``tf2_msgs/TFMessage`` (any class flavour);
        returns how many were added (refused ones are counted in :attr:`invalid`)."""
        added = 0
        for stamped in msg.transforms:
            t, q = stamped.transform.translation, stamped.transform.rotation
            transform = Transform((t.x, t.y, t.z), (q.x, q.y, q.z, q.w))
            stamp = None if static else stamp_to_ns(stamped.header.stamp)
            added += self.set_transform(stamped.header.frame_id, stamped.child_frame_id, transform, stamp)
        return added

    def forget_before(self, stamp_ns: int) -> None:
        """Drop the dynamic samples no lookup at ``stamp_ns`` or later needs (a reader streaming a long
        bag keeps its memory bounded, as tf2's buffer keeps a limited cache)."""
        for series in self._dynamic.values():
            series.forget_before(stamp_ns)

    def clear_dynamic(self) -> None:
        """Forget every ``/tf`` sample, keep ``/tf_static``: what tf2 does when the clock jumps back
        (a looped bag or a reset simulator sends the same stamps with other poses; static
        transforms are not sent again, their publishers latch them once)."""
        self._dynamic.clear()

    def newest_stamp(self) -> int:
        """The newest ``/tf`` sample's stamp (ns), 0 when there is none."""
        return max((series.stamps[-1] for series in self._dynamic.values() if series.stamps), default=0)

    def static_edge(self, child: str) -> tuple[str, Transform] | None:
        """The static edge ``parent <- child`` (``/tf_static``) as ``(parent, transform)``, or None."""
        return self._static.get(frame_name(child))

    def frames(self) -> set[str]:
        """Every frame named by an edge."""
        names = set(self._static) | set(self._dynamic)
        names |= {parent for parent, _ in self._static.values()} | {s.parent for s in self._dynamic.values()}
        return names

    def _edge(self, child: str, stamp_ns: int) -> tuple[str, Transform] | None:
        if child in self._static:
            return self._static[child]
        series = self._dynamic.get(child)
        if series is None:
            return None
        transform = series.at(stamp_ns)
        return None if transform is None else (series.parent, transform)

    def _up(self, frame: str, stamp_ns: int) -> dict[str, Transform]:
        """``ancestor <- frame`` for ``frame`` and every ancestor reachable at ``stamp_ns``."""
        chain = {frame: IDENTITY}
        current, to_frame = frame, IDENTITY
        for _ in range(MAX_DEPTH):
            edge = self._edge(current, stamp_ns)
            if edge is None or edge[0] in chain:  # the root, a gap in time, or a loop
                break
            parent, transform = edge
            to_frame = transform @ to_frame
            chain[parent] = to_frame
            current = parent
        return chain

    def lookup(self, target: str, source: str, stamp_ns: int) -> Transform | None:
        """``target <- source`` at ``stamp_ns`` (maps points of ``source`` into ``target``), or None
        when the frames are not connected at that stamp (unknown frame, or extrapolation)."""
        target, source = frame_name(target), frame_name(source)
        if target == source:
            return IDENTITY
        from_source = self._up(source, stamp_ns)
        if target in from_source:
            return from_source[target]
        from_target = self._up(target, stamp_ns)
        for ancestor, ancestor_from_target in from_target.items():
            if ancestor in from_source:
                return ancestor_from_target.inverse() @ from_source[ancestor]
        return None
