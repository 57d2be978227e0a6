"""Read a rosbag2 (MCAP or sqlite3) back into :class:`~pcc_ros.types.Sample` objects.

The offline tools (extraction, replay, evaluation) consume bags through this one function,
whether the bag came from ``pcc convert`` or from ``ros2 bag record``:

- every ``sensor_msgs/PointCloud2`` on the points topic is one frame (stamp and frame id
  from its header; all numeric count-1 fields become float32 columns, x, y, z first;
  points with a non-finite coordinate are dropped, as organized sensor clouds pad with NaN);
- ``Detection3DArray`` messages on the detections / ground-truth topics join the frame
  whose header stamp they carry; boxes in another frame than the scan are moved into the
  scan's frame at that stamp, as the node core moves them (a frame whose transform is
  unknown is skipped as malformed);
- ``/tf`` and ``/tf_static`` go into a :class:`~pcc_ros.msg.tf_buffer.TransformBuffer`, the
  tf tree the nodes and ``pcc replay`` use: the pose is its ``odom <- sensor`` at the scan's
  stamp (a ``/tf`` sample at that stamp, or the interpolation of the two around it; ``None``
  when odom is not reachable then), and ``extras["sensor_to_base"]`` is the static
  ``base_link <- sensor`` when the bag has one;
- ``sequence`` / ``index`` come from the ``pcc_ros.frames`` custom data that
  :func:`pcc_ros.data.bag_writer.write_bag` stores, else ``""`` / the frame's ordinal.

Messages are grouped by header stamp while reading in bag-time order; a group is complete
once the bag time has moved ``window_ns`` past its first message (recorded bags stamp
detections after the scan they belong to). Box messages whose scan never came are counted
and logged, never silently attached to another frame.

Integrity: every reader of the package goes through :func:`open_bag`,
:func:`iter_messages` and :func:`decode`. Storage damage (an MCAP chunk whose CRC or
compression fails, a truncated file, a corrupt sqlite3 database) is a :class:`BagError`
naming the file and, for MCAP, the byte offset of the damaged chunk; a topic whose type is
not the expected one is a :class:`BagError` naming topic and type; a single message that
does not deserialize is skipped, counted (:class:`ReadStats`) and logged, never passed on.
"""

from __future__ import annotations

import json
import logging
import sqlite3
import struct
from collections import Counter
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from mcap.reader import make_reader
from mcap.stream_reader import StreamReader, get_chunk_data_stream
from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.rosbag2 import ReaderError
from rosbags.typesys.base import TypesysError

from pcc_ros.data.bag_writer import (
    BASE_FRAMES,
    DETECTIONS_TOPIC,
    FRAMES_KEY,
    GROUND_TRUTH_TOPIC,
    POINTS_TOPIC,
    TF_STATIC_TOPIC,
    TF_TOPIC,
    WORLD_FRAMES,
)
from pcc_ros.errors import BagError, DataError, PccError
from pcc_ros.msg.detections import decode_detection_array
from pcc_ros.msg.pointcloud2 import read_xyz
from pcc_ros.msg.stamps import stamp_to_ns
from pcc_ros.msg.tf_buffer import TransformBuffer, same_frame
from pcc_ros.msg.typestore import get_typestore
from pcc_ros.types import Sample

log = logging.getLogger(__name__)

_NUMERIC_DATATYPES = range(1, 9)
#: How far before the oldest pending stamp :func:`read_frames` keeps ``/tf`` samples (tf2's default cache).
TF_CACHE_NS = 10_000_000_000


@dataclass
class _Group:
    """Messages sharing one header stamp."""

    first_time: int
    cloud: object = None
    detections: object = None
    ground_truth: object = None


def _boxes_in(msg, frame_id: str, tf: TransformBuffer):
    """The boxes of a Detection3DArray in the scan's frame ``frame_id``: boxes given in another
    frame are moved by ``tf`` at the array's stamp, as the node core moves them (replay, live)."""
    source = str(msg.header.frame_id)
    transform = None
    if source and not same_frame(source, frame_id):
        transform = tf.lookup(frame_id, source, stamp_to_ns(msg.header.stamp))
        if transform is None:
            raise DataError(f"boxes in frame '{source}' but no transform '{source}' -> '{frame_id}' at their stamp "
                            "in the bag's /tf and /tf_static")
    return decode_detection_array(msg, transform=transform)[0]


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


def _storage_errors() -> tuple[type[BaseException], ...]:
    """Exceptions the storage layers raise on damaged bytes (rosbags, zstd, lz4, sqlite)."""
    errors: list[type[BaseException]] = [
        AnyReaderError, ReaderError, TypesysError, OSError, EOFError, struct.error, ValueError, KeyError,
        IndexError, TypeError, RuntimeError,  # lz4 raises RuntimeError on a damaged frame
        # a damaged length field makes rosbags' mcap reader ask for petabytes in one read(): the
        # allocation fails at once (nothing was held), so it is damage, named as such below
        MemoryError,
        # a damaged offset or count in an MCAP index can exceed what a seek / slice accepts
        OverflowError,
    ]
    try:
        from rosbags.rosbag2 import storage_mcap

        errors.append(storage_mcap.zstd.ZstdError)
    except (ImportError, AttributeError):
        pass
    try:
        import apsw

        errors.append(apsw.Error)
    except ImportError:
        pass

    errors.append(sqlite3.Error)
    return tuple(errors)


def _bag_files(path: Path) -> list[Path]:
    if path.is_file():
        return [path]
    return sorted([*path.glob("*.mcap"), *path.glob("*.db3")]) if path.is_dir() else []


def mcap_chunk_damage(file: str | Path) -> str | None:
    """``"<file>@<offset>: <what>"`` for the first MCAP chunk whose compression or CRC fails,
    ``"<file>: <what>"`` for an unreadable summary, or None when every chunk checks out.

    Chunks written without a CRC (``uncompressed_crc == 0``) are only decompressed.
    """
    file = Path(file)
    try:
        with file.open("rb") as stream:
            summary = make_reader(stream).get_summary()
            if summary is None:
                return f"{file}: MCAP file has no summary section (truncated or still being recorded?)"
            for index in sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset):
                stream.seek(index.chunk_start_offset)
                try:
                    chunk = next(iter(StreamReader(stream, skip_magic=True, emit_chunks=True).records))
                    get_chunk_data_stream(chunk, validate_crc=True)
                except Exception as exc:  # any decoder's error (zstandard, lz4, CRC) locates the damage
                    return f"{file}@{index.chunk_start_offset}: damaged MCAP chunk ({type(exc).__name__}: {exc})"
    except Exception as exc:
        return f"{file}: unreadable MCAP file ({type(exc).__name__}: {exc})"
    return None


def _is_sqlite_error(exc: BaseException) -> bool:
    try:
        import apsw
    except ImportError:  # pragma: no cover - rosbags depends on apsw
        return isinstance(exc, sqlite3.Error)
    return isinstance(exc, (apsw.Error, sqlite3.Error))


def _damaged(path: Path, exc: BaseException, opening: bool = False) -> BagError:
    """The :class:`BagError` for a storage failure on ``path``: where (file, MCAP offset), what to do."""
    where = None
    files = _bag_files(path)
    if _is_sqlite_error(exc):
        where = next((f"{f}: sqlite3 database is corrupt" for f in files if f.suffix == ".db3"), None)
    elif not opening or isinstance(exc, (ReaderError, EOFError, struct.error)) or "zstd" in type(exc).__module__:
        where = next((d for f in files if f.suffix == ".mcap" and (d := mcap_chunk_damage(f))), None)
    detail = f"{type(exc).__name__}: {exc}"
    if isinstance(exc, MemoryError):
        detail = "a record's length field asks for more bytes than memory holds (MemoryError): the length is damaged"
    if opening:
        return BagError(
            f"{where or path}: cannot open bag ({detail})",
            hint="check that it is a complete rosbag2 (metadata.yaml + .mcap / .db3); re-copy, re-record or convert it",
        )
    sqlite = any(f.suffix == ".db3" for f in files)
    return BagError(
        where or f"{path}: damaged bag ({detail})",
        hint="the bag's bytes are corrupted; re-copy or re-record it"
        + (" (or salvage it with `sqlite3 FILE .recover`)" if sqlite else ""),
    )


class BagReader(AnyReader):
    """rosbags' :class:`AnyReader`, already open when :func:`open_bag` returns it; as a
    context manager (rosbags' own habit) it closes on leaving the block."""

    def __enter__(self) -> BagReader:
        return self  # opened by open_bag, which names the path when that fails


def open_bag(path: str | Path) -> BagReader:
    """An open rosbag2 reader (directory, ``.mcap`` or ``.db3``) with pcc_ros's type store;
    :class:`BagError` naming the path when it is not a readable bag.

    Use it as ``with open_bag(path) as reader: ...`` (closed on leaving the block);
    ``reader.close()`` in a ``finally`` does the same."""
    path = Path(path)
    if not path.exists():
        raise BagError(f"{path}: cannot open bag (no such file or directory)", hint="check the path")
    try:
        reader = BagReader([path], default_typestore=get_typestore())
        reader.open()
    except _storage_errors() as exc:
        raise _damaged(path, exc, opening=True) from exc
    return reader


def iter_messages(reader: AnyReader, path: str | Path, connections: Iterable) -> Iterator[tuple]:
    """``reader.messages(connections=...)`` with storage damage raised as :class:`BagError`.

    A read to the end also checks that every connection gave as many messages as the bag's
    index lists (``msgcount``): a damaged MCAP summary can make the reader skip a whole chunk
    without any error, which would otherwise be silent data loss."""
    connections = list(connections)
    if not connections:  # rosbags reads every topic for an empty list; none asked for is none read
        return
    messages = reader.messages(connections=connections)
    seen: Counter = Counter()
    while True:
        try:
            item = next(messages)
        except StopIteration:
            break
        except _storage_errors() as exc:
            raise _damaged(Path(path), exc) from exc
        seen[item[0].id] += 1
        yield item
    missing = [f"{c.topic} {seen[c.id]} of {c.msgcount}" for c in connections if seen[c.id] < (c.msgcount or 0)]
    if missing:
        raise BagError(f"{path}: damaged: fewer messages readable than its index lists ({', '.join(missing)})")


@dataclass
class ReadStats:
    """What a bag pass skipped, by topic: undecodable messages and (for frames) malformed ones."""

    undecodable: Counter = field(default_factory=Counter)
    malformed: Counter = field(default_factory=Counter)
    first_problem: str = ""

    def note(self, kind: str, topic: str, text: str) -> None:
        getattr(self, kind)[topic] += 1
        if not self.first_problem:
            self.first_problem = text

    @property
    def skipped(self) -> int:
        return sum(self.undecodable.values()) + sum(self.malformed.values())

    def describe(self) -> str:
        parts = [f"{n} undecodable {t}" for t, n in sorted(self.undecodable.items())]
        parts += [f"{n} malformed {t}" for t, n in sorted(self.malformed.items())]
        return ", ".join(parts)


def decode(reader: AnyReader, raw, connection, time_ns: int, path: str | Path):
    """Deserialize one message; :class:`BagError` naming bag, topic and bag time when it cannot be."""
    try:
        return reader.deserialize(raw, connection.msgtype)
    except (*_storage_errors(), AssertionError, UnicodeDecodeError) as exc:
        raise BagError(
            f"{path}: {connection.topic} message at bag time {time_ns} is undecodable "
            f"({type(exc).__name__}: {exc})"
        ) from None


def check_topic_types(
    reader: AnyReader, path: str | Path, expected: dict[str, str], required: Iterable[str] = ()
) -> None:
    """:class:`BagError` if a topic of ``expected`` exists with another type, or a ``required`` one is missing."""
    topics: dict[str, set[str]] = {}
    for c in reader.connections:
        topics.setdefault(c.topic, set()).add(c.msgtype)
    for topic in required:
        if topic not in topics:
            raise BagError(
                f"{path}: no {topic} topic (topics: {', '.join(sorted(topics)) or 'none'})",
                hint="name the right topic with the command's --*-topic option",
            )
    for topic, msgtype in expected.items():
        wrong = topics.get(topic, set()) - {msgtype}
        if wrong:
            raise BagError(
                f"{path}: topic {topic} has type {', '.join(sorted(wrong))}, expected {msgtype}",
                hint="name the topic that carries that type with the command's --*-topic option",
            )


#: Topic -> type that :func:`read_frames` expects.
POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
DETECTION3DARRAY = "vision_msgs/msg/Detection3DArray"
TFMESSAGE = "tf2_msgs/msg/TFMessage"


def read_frames(
    bag: str | Path,
    points_topic: str = POINTS_TOPIC,
    detections_topic: str = DETECTIONS_TOPIC,
    ground_truth_topic: str = GROUND_TRUTH_TOPIC,
    window_ns: int = 200_000_000,
    stats: ReadStats | None = None,
) -> Iterator[Sample]:
    """Frames of a rosbag2 directory, ``.mcap`` or ``.db3`` (see the module docstring).

    Undecodable messages and malformed frames are skipped, logged and counted in
    ``stats``; a bag where every scan was skipped is a :class:`BagError`.
    """
    path = Path(bag)
    stats = ReadStats() if stats is None else stats
    yielded = 0
    with open_bag(path) as reader:
        expected = {points_topic: POINTCLOUD2, detections_topic: DETECTION3DARRAY,
                    ground_truth_topic: DETECTION3DARRAY, TF_TOPIC: TFMESSAGE, TF_STATIC_TOPIC: TFMESSAGE}
        check_topic_types(reader, path, expected, required=[points_topic])
        connections = [c for c in reader.connections if c.topic in expected]
        names = _frame_names(_bag_frames_runs(reader))
        tf = TransformBuffer()
        groups: dict[int, _Group] = {}
        orphans = 0

        def flush(before: int | None) -> Iterator[Sample]:
            nonlocal orphans, yielded
            for stamp in sorted(groups):
                group = groups[stamp]
                if before is not None and group.first_time > before:
                    break  # later stamps are newer still: keep the output in stamp order
                del groups[stamp]
                if group.cloud is None:
                    # boxes without their scan are worth a warning; /tf alone (100 Hz) is normal
                    orphans += group.detections is not None or group.ground_truth is not None
                    continue
                name = next(names)
                try:
                    frame = _frame(group, stamp, tf, *name, path)
                except DataError as exc:
                    stats.note("malformed", points_topic, str(exc))
                    log.warning("skipped %s", exc)
                    continue
                yielded += 1
                yield frame

        for connection, time_ns, raw in iter_messages(reader, path, connections):
            topic = connection.topic
            try:
                msg = decode(reader, raw, connection, time_ns, path)
                if topic in (TF_TOPIC, TF_STATIC_TOPIC):
                    refused = tf.invalid
                    tf.add_message(msg, static=topic == TF_STATIC_TOPIC)
                    if tf.invalid > refused:
                        raise DataError(f"{path}: {topic} message at bag time {time_ns}: "
                                        f"{tf.invalid - refused} transform(s) not rigid, left out")
                else:
                    stamp = stamp_to_ns(msg.header.stamp)
            except PccError as exc:
                stats.note("undecodable", topic, str(exc))
                log.warning("skipped: %s", exc)
                continue
            if topic not in (TF_TOPIC, TF_STATIC_TOPIC):
                group = groups.setdefault(stamp, _Group(time_ns))
                slot = {points_topic: "cloud", detections_topic: "detections", ground_truth_topic: "ground_truth"}
                setattr(group, slot[topic], msg)
            yield from flush(time_ns - window_ns - 1)
            if groups:  # /tf samples older than tf2's cache before the pending scans are needed no more
                tf.forget_before(min(groups) - TF_CACHE_NS)
        yield from flush(None)
        if orphans:
            log.warning("%s: %d stamps had boxes but no %s scan", path, orphans, points_topic)
    if stats.skipped:
        log.warning("%s: skipped %s", path, stats.describe())
        if not yielded:
            raise BagError(
                f"{path}: no usable {points_topic} scan ({stats.describe()}; first: {stats.first_problem})",
                hint="check the recording; `pcc info` lists the topics and counts",
            )


def _frame(group: _Group, stamp: int, tf: TransformBuffer, sequence: str, index: int, path: Path) -> Sample:
    cloud = group.cloud
    frame_id = str(cloud.header.frame_id)
    try:
        fields = cloud_fields(cloud)
        points = read_xyz(cloud, extra_fields=fields[3:])
        detections, truth = (None if msg is None else _boxes_in(msg, frame_id, tf)
                             for msg in (group.detections, group.ground_truth))
    except PccError as exc:
        raise DataError(f"{path}: frame at stamp {stamp}: {exc}") from exc
    extras: dict = {}
    mount = tf.static_edge(frame_id)
    if mount is not None and mount[0] in BASE_FRAMES:
        extras["sensor_to_base"] = mount[1].matrix()
        extras["base_frame"] = mount[0]
    elif frame_id in BASE_FRAMES:
        extras["base_frame"] = frame_id
    pose = None
    for world in WORLD_FRAMES:  # the first world frame the scan's frame reaches at its stamp
        pose = tf.lookup(world, frame_id, stamp)
        if pose is not None:
            extras["world_frame"] = world
            break
    return Sample(
        stamp_ns=stamp,
        frame_id=frame_id,
        points=points,
        fields=fields,
        detections=detections,
        ground_truth=truth,
        pose=None if pose is None else pose.matrix(),
        sequence=sequence,
        index=index,
        extras=extras,
    )
