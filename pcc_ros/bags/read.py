"""Read a rosbag2 (MCAP or sqlite3) back into :class:`~pcc_ros.frame.Frame` objects.

The offline tools (extraction, replay, evaluation) consume bags through this one function,
whether the bag came from ``pcc convert`` or from ``ros2 bag record``:

- every ``sensor_msgs/PointCloud2`` on the points topic is one frame (stamp and frame id
  from its header; all numeric count-1 fields become float32 columns, x, y, z first;
  points with a non-finite coordinate are dropped, as organized sensor clouds pad with NaN);
- ``Detection3DArray`` messages on the detections / ground-truth topics join the frame
  whose header stamp they carry;
- the pose is ``odom <- sensor`` composed from ``/tf`` (dynamic, same stamp, or the latest
  one within ``window_ns`` before) and ``/tf_static``; ``extras["sensor_to_base"]`` is the
  static ``base_link <- sensor`` when the bag has one;
- ``sequence`` / ``index`` come from the ``pcc_ros.frames`` custom data that
  :func:`pcc_ros.bags.convert.write_bag` stores, else ``""`` / the frame's ordinal.

Messages are grouped by header stamp while reading in bag-time order; a group is complete
once the bag time has moved ``window_ns`` past its first message (recorded bags stamp
detections after the scan they belong to). Box messages whose scan never came are counted
and logged, never silently attached to another frame.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.rosbag2 import ReaderError
from scipy.spatial.transform import Rotation

from pcc_ros.bags.convert import (
    BASE_FRAME,
    DETECTIONS_TOPIC,
    FRAMES_KEY,
    GROUND_TRUTH_TOPIC,
    ODOM_FRAME,
    POINTS_TOPIC,
    TF_STATIC_TOPIC,
    TF_TOPIC,
)
from pcc_ros.errors import DataError, PccError
from pcc_ros.frame import Frame
from pcc_ros.msg.detections import boxes_from_detection_array
from pcc_ros.msg.pointcloud2 import read_xyz
from pcc_ros.msg.stamps import stamp_to_ns
from pcc_ros.msg.typestore import get_typestore

log = logging.getLogger(__name__)

_NUMERIC_DATATYPES = range(1, 9)


@dataclass
class _Group:
    """Messages sharing one header stamp."""

    first_time: int
    cloud: object = None
    detections: object = None
    ground_truth: object = None
    tf: dict = field(default_factory=dict)


def transform_to_matrix(transform) -> np.ndarray:
    """``4x4`` of a ``geometry_msgs/Transform``."""
    t, q = transform.translation, transform.rotation
    out = np.eye(4)
    quat = np.array([q.x, q.y, q.z, q.w], dtype=np.float64)
    if not (np.isfinite(quat).all() and np.linalg.norm(quat) > 1e-9):
        raise DataError(f"transform has an invalid rotation {quat.tolist()}")
    out[:3, :3] = Rotation.from_quat(quat).as_matrix()
    out[:3, 3] = [t.x, t.y, t.z]
    return out


def cloud_fields(msg) -> tuple[str, ...]:
    """x, y, z then every other numeric single-count field, in message order."""
    names = [f.name for f in msg.fields if int(f.count) == 1 and int(f.datatype) in _NUMERIC_DATATYPES]
    missing = {"x", "y", "z"} - set(names)
    if missing:
        raise DataError(f"PointCloud2 in {msg.header.frame_id!r} lacks fields {sorted(missing)}")
    return ("x", "y", "z", *(n for n in names if n not in ("x", "y", "z")))


def _bag_frames_runs(reader: AnyReader) -> list[tuple[str, int, int]]:
    try:
        custom = reader.readers[0].storage.metadata.custom or {}
        runs = json.loads(custom.get(FRAMES_KEY, "[]"))
        return [(str(s), int(i), int(n)) for s, i, n in runs]
    except (AttributeError, ValueError, TypeError):
        return []


def _frame_names(runs: list[tuple[str, int, int]]) -> Iterator[tuple[str, int]]:
    for sequence, first, count in runs:
        for k in range(count):
            yield sequence, first + k
    ordinal = 0
    while True:  # frames beyond the recorded runs (or a bag without them)
        yield "", ordinal
        ordinal += 1


class _Tf:
    """Static edges, and dynamic edges by child frame with their stamps."""

    def __init__(self) -> None:
        self.static: dict[str, tuple[str, np.ndarray]] = {}
        self.latest: dict[str, tuple[int, str, np.ndarray]] = {}

    def chain(self, frame_id: str, stamp: int, group_tf: dict, window_ns: int) -> np.ndarray | None:
        """``odom <- frame_id`` through at most 16 edges, or None if it needs no dynamic edge / is broken."""
        matrix, current, dynamic = np.eye(4), frame_id, False
        for _ in range(16):
            if current == ODOM_FRAME:
                return matrix if dynamic else None
            if current in group_tf:
                parent, edge = group_tf[current]
                dynamic = True
            elif current in self.latest and 0 <= stamp - self.latest[current][0] <= window_ns:
                _, parent, edge = self.latest[current]
                dynamic = True
            elif current in self.static:
                parent, edge = self.static[current]
            else:
                return None
            matrix = edge @ matrix
            current = parent
        return None


def open_bag(path: str | Path) -> AnyReader:
    """An open rosbag2 reader (directory, ``.mcap`` or ``.db3``) with pcc_ros's type store;
    :class:`DataError` naming the path when it is not a readable bag. The caller closes it."""
    path = Path(path)
    try:
        reader = AnyReader([path], default_typestore=get_typestore())
        reader.open()
    except (AnyReaderError, ReaderError, FileNotFoundError, OSError) as exc:
        raise DataError(f"{path}: cannot open bag ({exc})") from exc
    return reader


def read_frames(
    bag: str | Path,
    points_topic: str = POINTS_TOPIC,
    detections_topic: str = DETECTIONS_TOPIC,
    ground_truth_topic: str = GROUND_TRUTH_TOPIC,
    window_ns: int = 200_000_000,
) -> Iterator[Frame]:
    """Frames of a rosbag2 directory, ``.mcap`` or ``.db3`` (see the module docstring)."""
    path = Path(bag)
    reader = open_bag(path)
    try:
        if not any(c.topic == points_topic for c in reader.connections):
            topics = sorted({c.topic for c in reader.connections})
            raise DataError(f"{path}: no {points_topic} topic (topics: {', '.join(topics) or 'none'})")
        wanted = {points_topic, detections_topic, ground_truth_topic, TF_TOPIC, TF_STATIC_TOPIC}
        connections = [c for c in reader.connections if c.topic in wanted]
        names = _frame_names(_bag_frames_runs(reader))
        tf = _Tf()
        groups: dict[int, _Group] = {}
        orphans = 0

        def flush(before: int | None) -> Iterator[Frame]:
            nonlocal orphans
            for stamp in sorted(groups):
                group = groups[stamp]
                if before is not None and group.first_time > before:
                    break  # later stamps are newer still: keep the output in stamp order
                del groups[stamp]
                if group.cloud is None:
                    # boxes without their scan are worth a warning; /tf alone (100 Hz) is normal
                    orphans += group.detections is not None or group.ground_truth is not None
                    continue
                yield _frame(group, stamp, tf, window_ns, *next(names), path)

        for connection, time_ns, raw in reader.messages(connections=connections):
            try:
                msg = reader.deserialize(raw, connection.msgtype)
            except (AnyReaderError, PccError, ValueError) as exc:
                raise DataError(f"{path}: undecodable {connection.topic} message at {time_ns} ({exc})") from exc
            topic = connection.topic
            if topic in (TF_TOPIC, TF_STATIC_TOPIC):
                for t in msg.transforms:
                    edge = (t.header.frame_id, transform_to_matrix(t.transform))
                    if topic == TF_STATIC_TOPIC:
                        tf.static[t.child_frame_id] = edge
                    else:
                        stamp = stamp_to_ns(t.header.stamp)
                        groups.setdefault(stamp, _Group(time_ns)).tf[t.child_frame_id] = edge
                        tf.latest[t.child_frame_id] = (stamp, *edge)
            else:
                stamp = stamp_to_ns(msg.header.stamp)
                group = groups.setdefault(stamp, _Group(time_ns))
                slot = {points_topic: "cloud", detections_topic: "detections", ground_truth_topic: "ground_truth"}
                setattr(group, slot[topic], msg)
            yield from flush(time_ns - window_ns - 1)
        yield from flush(None)
        if orphans:
            log.warning("%s: %d stamps had boxes but no %s scan", path, orphans, points_topic)
    finally:
        reader.close()


def _frame(group: _Group, stamp: int, tf: _Tf, window_ns: int, sequence: str, index: int, path: Path) -> Frame:
    cloud = group.cloud
    frame_id = str(cloud.header.frame_id)
    try:
        fields = cloud_fields(cloud)
        points = read_xyz(cloud, extra_fields=fields[3:])
        detections = None if group.detections is None else boxes_from_detection_array(group.detections)
        truth = None if group.ground_truth is None else boxes_from_detection_array(group.ground_truth)
    except PccError as exc:
        raise DataError(f"{path}: frame at stamp {stamp}: {exc}") from exc
    extras: dict = {}
    if frame_id in tf.static and tf.static[frame_id][0] == BASE_FRAME:
        extras["sensor_to_base"] = tf.static[frame_id][1]
    return Frame(
        stamp_ns=stamp,
        frame_id=frame_id,
        points=points,
        fields=fields,
        detections=detections,
        ground_truth=truth,
        pose=tf.chain(frame_id, stamp, group.tf, window_ns),
        sequence=sequence,
        index=index,
        extras=extras,
    )
