"""Write :class:`~pcc_ros.types.Sample` streams to a rosbag2 (version 9, MCAP or sqlite3).

One frame becomes, all stamped with the frame's ``stamp_ns`` (header stamp and bag time):

- ``/points`` ``sensor_msgs/PointCloud2`` (the frame's columns as float32 fields:
  x, y, z, intensity[, ring]);
- ``/ground_truth`` ``vision_msgs/Detection3DArray`` (``id`` = track id, score 1) when
  the frame has ground truth;
- ``/detections`` ``vision_msgs/Detection3DArray`` (detector label and raw score) when
  the frame has detector results; the topic is absent from bags without any;
- ``/tf`` ``tf2_msgs/TFMessage`` ``odom -> base_link`` when the frame has a pose, and
  ``/tf_static`` ``base_link -> <sensor frame>`` (transient-local, as robot_state_publisher
  offers it, so ``ros2 bag play`` latches it), written at the start and again whenever
  the mounting changes. Without ``extras["sensor_to_base"]`` base_link is the sensor itself.
  A source with its own frame names sets ``extras["world_frame"]`` / ``extras["base_frame"]``
  (Argoverse 2: ``city -> ego_vehicle``) and may add the other sensors' mountings as
  ``extras["static_edges"]`` (``(parent, child, parent <- child)``), published with the scan's.

Boxes without 3D extent (KITTI ``DontCare`` rows: size -1, position -1000) cannot be a
``BoundingBox3D``; they are left out of ``/ground_truth`` and counted in the log, never
written as fake boxes.

The message definitions are embedded (rosbags writes them into the MCAP schemas / the
sqlite3 ``message_definitions`` table), which Foxglove and ``ros2 bag play`` need for
``vision_msgs`` on machines without it. MCAP bags are zstd-compressed per chunk (the
rosbag2 ``storage`` compression that ``ros2 bag`` reads natively). The bag is written in a
temporary directory next to ``out`` and renamed into place only when complete, so a
failure or Ctrl-C never leaves a partial bag behind.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import struct
import tempfile
import zlib
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

import numpy as np
from mcap.reader import make_reader
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer, storage_mcap
from scipy.spatial.transform import Rotation
from tqdm import tqdm

from pcc_ros.errors import DataError, PccError
from pcc_ros.msg.detections import detection_array_from_boxes
from pcc_ros.msg.pointcloud2 import create_cloud
from pcc_ros.msg.stamps import make_header
from pcc_ros.msg.typestore import get_typestore, new_message
from pcc_ros.types import Boxes, Sample

log = logging.getLogger(__name__)

POINTS_TOPIC = "/points"
DETECTIONS_TOPIC = "/detections"
GROUND_TRUTH_TOPIC = "/ground_truth"
TF_TOPIC = "/tf"
TF_STATIC_TOPIC = "/tf_static"
ODOM_FRAME = "odom"
BASE_FRAME = "base_link"
#: Frames a pose is read against, in order (:func:`pcc_ros.data.bag.read_frames`): the package's
#: ``odom``, Argoverse 2's ``city``, REP 105's ``map``; and the vehicle frames a mounting hangs from.
WORLD_FRAMES = (ODOM_FRAME, "city", "map")
BASE_FRAMES = (BASE_FRAME, "ego_vehicle")
STORAGES = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}
#: Suffixes of rosbag2 storage files: an output named so is refused (a bag is the folder around one).
BAG_FILE_SUFFIXES = (".mcap", ".db3")
#: rosbag2 custom_data key holding the frames' (sequence, first index, count) runs.
FRAMES_KEY = "pcc_ros.frames"
SOURCE_KEY = "pcc_ros.source"

_INFINITE = QosTime(2147483647, 4294967295)
#: What tf2's static broadcaster offers; recorded so ``ros2 bag play`` re-offers it latched.
TF_STATIC_QOS = Qos(
    QosHistory.KEEP_LAST, 1, QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL,
    _INFINITE, _INFINITE, QosLiveliness.AUTOMATIC, _INFINITE, False,
)


@dataclass
class BagSummary:
    """What :func:`write_bag` wrote."""

    path: Path
    frames: int = 0
    messages: dict[str, int] = field(default_factory=dict)
    skipped_boxes: int = 0
    bytes: int = 0


def matrix_to_transform(matrix: np.ndarray, classes=None):
    """``geometry_msgs/Transform`` of a ``4x4`` rigid transform."""
    matrix = np.asarray(matrix, dtype=np.float64)
    if matrix.shape != (4, 4) or not np.isfinite(matrix).all():
        raise DataError(f"pose is not a finite 4x4 matrix: {matrix.tolist()}")
    x, y, z, w = Rotation.from_matrix(matrix[:3, :3]).as_quat()
    t = matrix[:3, 3]
    return new_message(
        "geometry_msgs/msg/Transform",
        classes,
        translation=new_message("geometry_msgs/msg/Vector3", classes, x=float(t[0]), y=float(t[1]), z=float(t[2])),
        rotation=new_message("geometry_msgs/msg/Quaternion", classes, x=float(x), y=float(y), z=float(z), w=float(w)),
    )


def tf_message(edges: list[tuple[str, str, np.ndarray]], stamp_ns: int, classes=None):
    """``tf2_msgs/TFMessage`` of ``(parent, child, parent <- child)`` edges."""
    transforms = [
        new_message(
            "geometry_msgs/msg/TransformStamped",
            classes,
            header=make_header(parent, stamp_ns, classes),
            child_frame_id=child,
            transform=matrix_to_transform(matrix, classes),
        )
        for parent, child, matrix in edges
    ]
    return new_message("tf2_msgs/msg/TFMessage", classes, transforms=transforms)


class _FrameRuns:
    """Run-length record of (sequence, index) per frame, stored in the bag's custom_data."""

    def __init__(self) -> None:
        self.runs: list[list] = []

    def add(self, sequence: str, index: int) -> None:
        if self.runs and self.runs[-1][0] == sequence and self.runs[-1][1] + self.runs[-1][2] == index:
            self.runs[-1][2] += 1
        else:
            self.runs.append([sequence, int(index), 1])

    def dumps(self) -> str:
        return json.dumps(self.runs, separators=(",", ":"))


class BagWriter:
    """One open rosbag2 writer plus the lazily added connections."""

    def __init__(self, writer: Writer) -> None:
        self.writer = writer
        self.store = get_typestore()
        self.connections: dict[str, object] = {}
        self.counts: dict[str, int] = {}

    def write(self, topic: str, msgtype: str, msg, stamp_ns: int, qos: Qos | None = None) -> None:
        self.write_raw(topic, msgtype, self.store.serialize_cdr(msg, msgtype), stamp_ns, qos)

    def write_raw(self, topic: str, msgtype: str, raw: bytes, stamp_ns: int, qos: Qos | None = None) -> None:
        """Write an already CDR-serialised message (copying records between bags)."""
        if topic not in self.connections:
            self.connections[topic] = self.writer.add_connection(
                topic, msgtype, typestore=self.store, offered_qos_profiles=[qos] if qos else []
            )
            self.counts[topic] = 0
        self.writer.write(self.connections[topic], stamp_ns, raw)
        self.counts[topic] += 1


def _boxes_3d(boxes: Boxes) -> tuple[Boxes, int]:
    """Boxes that are real 3D boxes, and how many were not (DontCare and the like)."""
    valid = boxes.valid_mask()
    return (boxes, 0) if valid.all() else (boxes[valid], int(np.count_nonzero(~valid)))


def write_frames(bag: BagWriter, frames: Iterable[Sample], runs: _FrameRuns, summary: BagSummary) -> None:
    """Write every frame's messages (see the module docstring) and fill ``summary``."""
    last_stamp: int | None = None
    static: tuple | None = None
    for frame in frames:
        stamp = int(frame.stamp_ns)
        if last_stamp is not None and stamp <= last_stamp:
            raise DataError(
                f"frame {frame.sequence}:{frame.index} stamp {stamp} is not after the previous frame's {last_stamp}; "
                "frames of one bag must have increasing stamps (convert one sequence per bag)"
            )
        last_stamp = stamp
        try:
            cloud = create_cloud(frame.points, frame.fields, frame.frame_id, stamp)
        except PccError as exc:
            raise DataError(f"frame {frame.sequence}:{frame.index}: cannot build PointCloud2 ({exc})") from exc
        bag.write(POINTS_TOPIC, "sensor_msgs/msg/PointCloud2", cloud, stamp)
        for topic, boxes in ((GROUND_TRUTH_TOPIC, frame.ground_truth), (DETECTIONS_TOPIC, frame.detections)):
            if boxes is None:
                continue
            kept, skipped = _boxes_3d(boxes)
            summary.skipped_boxes += skipped
            msg = detection_array_from_boxes(kept, frame.frame_id, stamp)
            bag.write(topic, "vision_msgs/msg/Detection3DArray", msg, stamp)
        sensor_to_base = frame.extras.get("sensor_to_base")
        others = list(frame.extras.get("static_edges", ()))
        if frame.pose is not None or sensor_to_base is not None or others:
            world = str(frame.extras.get("world_frame", ODOM_FRAME))
            base = str(frame.extras.get("base_frame", BASE_FRAME))
            mount = np.eye(4) if sensor_to_base is None else np.asarray(sensor_to_base, dtype=np.float64)
            edges = [] if frame.frame_id == base else [(base, frame.frame_id, mount)]
            edges += [(str(p), str(c), np.asarray(m, dtype=np.float64)) for p, c, m in others if c != frame.frame_id]
            key = tuple((p, c, np.round(m, 12).tobytes()) for p, c, m in edges)
            if key != static and edges:
                static = key
                msg = tf_message(edges, stamp)
                bag.write(TF_STATIC_TOPIC, "tf2_msgs/msg/TFMessage", msg, stamp, qos=TF_STATIC_QOS)
            if frame.pose is not None:
                world_from_base = np.asarray(frame.pose, dtype=np.float64) @ np.linalg.inv(mount)
                bag.write(TF_TOPIC, "tf2_msgs/msg/TFMessage", tf_message([(world, base, world_from_base)],
                                                                          stamp), stamp)
        runs.add(frame.sequence, frame.index)
        summary.frames += 1


def check_output_bag(out: str | Path, force: bool = False) -> None:
    """Refuse an output bag path before any work (:func:`atomic_bag` checks it again): one named
    like a storage file (``x.mcap``, ``x.db3``: a rosbag2 bag is a folder, and rosbags would make
    a folder ``x.mcap/`` holding ``x.mcap.mcap``), an existing one without ``force``, and a
    non-empty folder that is not a bag."""
    out = Path(out)
    if out.suffix in BAG_FILE_SUFFIXES:
        raise DataError(f"{out}: name the bag folder, not a {out.suffix} file — a rosbag2 bag is a folder "
                        f"(metadata.yaml + the storage file, both written inside it): use {out.with_suffix('')}")
    if out.exists() and not force:
        raise DataError(f"{out} exists; pass --force to replace it")
    if out.is_dir() and not (out / "metadata.yaml").is_file() and any(out.iterdir()):
        raise DataError(f"{out} is a non-empty folder that is not a rosbag2 bag; refusing to replace it")


@contextmanager
def atomic_bag(
    out: str | Path,
    storage: str = "mcap",
    compress: bool = True,
    zstd_level: int | None = None,
    force: bool = False,
) -> Iterator[BagWriter]:
    """Open a rosbag2 writer whose bag appears at ``out`` only if the block completes.

    The bag is written in a temporary directory next to ``out`` and renamed into place
    at the end; any exception (or Ctrl-C) removes it, leaving an existing ``out`` intact.

    Raises :class:`DataError` for an unknown storage, an ``out`` named like a storage file
    (``x.mcap``, ``x.db3``: a rosbag2 bag is a folder), or if ``out`` exists without ``force``.
    """
    out = Path(out)
    if storage not in STORAGES:
        raise DataError(f"unknown storage {storage!r} (use {' or '.join(STORAGES)})")
    check_output_bag(out, force)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp_dir = Path(tempfile.mkdtemp(prefix=f".{out.name}.partial-", dir=out.parent))
    tmp_bag = tmp_dir / out.name
    writer = Writer(tmp_bag, version=9, storage_plugin=STORAGES[storage])
    if compress:
        mode = CompressionMode.STORAGE if storage == "mcap" else CompressionMode.MESSAGE
        writer.set_compression(mode, CompressionFormat.ZSTD)
    try:
        writer.open()
        if compress and storage == "mcap" and zstd_level is not None:
            _set_mcap_zstd_level(writer, zstd_level)
        crcs = _record_chunk_crcs(writer) if storage == "mcap" else None
        yield BagWriter(writer)
        writer.close()
        if crcs is not None:
            _write_chunk_crcs(tmp_bag, crcs)
        if out.exists():  # force: replace only now that the new bag is complete
            shutil.rmtree(out) if out.is_dir() else out.unlink()
        os.replace(tmp_bag, out)
    except BaseException:
        if writer.storage is not None:
            writer.abort()
        raise
    finally:
        shutil.rmtree(tmp_dir, ignore_errors=True)


def write_bag(
    frames: Iterable[Sample],
    out: str | Path,
    storage: str = "mcap",
    compress: bool = True,
    zstd_level: int | None = None,
    force: bool = False,
    progress: bool = True,
    total: int | None = None,
    source: str = "",
) -> BagSummary:
    """Write ``frames`` to the rosbag2 directory ``out`` (see the module docstring; ``out`` names
    the folder: ``bags/run`` holds ``metadata.yaml`` and ``run.mcap``).

    Args:
        storage: ``"mcap"`` (default) or ``"sqlite3"``.
        compress: zstd; MCAP per chunk (rosbag2 "storage" mode), sqlite3 per message.
        zstd_level: MCAP chunk compression level (None = zstd's default, 3). Level 1 is
            about twice as fast for ~15 % larger bags (``pcc bench convert`` measures both).
        force: replace an existing ``out`` (only after the new bag is complete).
        total: frame count for the progress bar.

    Raises :class:`DataError` if ``out`` exists without ``force`` or a frame is bad; the
    partial bag is removed in every failure case.
    """
    out = Path(out)
    summary = BagSummary(path=out)
    with atomic_bag(out, storage, compress, zstd_level, force) as bag:
        runs = _FrameRuns()
        stream = tqdm(frames, total=total, unit="frame", desc=f"writing {out.name}", disable=not progress)
        write_frames(bag, stream, runs, summary)
        if summary.frames == 0:
            raise DataError("no frames to write")
        bag.writer.set_custom_data(FRAMES_KEY, runs.dumps())
        if source:
            bag.writer.set_custom_data(SOURCE_KEY, source)
    summary.messages = dict(bag.counts)
    summary.bytes = sum(p.stat().st_size for p in out.iterdir())
    if summary.skipped_boxes:
        log.info("left out %d boxes without 3D extent (KITTI DontCare rows)", summary.skipped_boxes)
    return summary


#: Byte offset of ``uncompressed_crc`` in an MCAP Chunk record: opcode (1), record length (8),
#: message start / end time and uncompressed size (3 x 8).
_CHUNK_CRC_OFFSET = 1 + 8 + 24


def _record_chunk_crcs(writer: Writer) -> list[int]:
    """Make rosbags' MCAP writer remember the CRC32 of every chunk's uncompressed bytes.

    rosbags writes ``uncompressed_crc = 0`` ("no CRC"), which leaves a bit flip inside a
    chunk undetectable; :func:`_write_chunk_crcs` fills the recorded values in after close,
    so every reader (rosbags, the mcap library, ``ros2 bag``) verifies them.
    """
    storage = writer.storage
    if not hasattr(storage, "compressor"):
        raise DataError("this rosbags version's MCAP writer has no compressor to wrap")
    compress = storage.compressor
    crcs: list[int] = []

    def compress_with_crc(data: bytes) -> bytes:
        crcs.append(zlib.crc32(data))
        return compress(data)

    storage.compressor = compress_with_crc
    return crcs


def _write_chunk_crcs(bag: Path, crcs: list[int]) -> None:
    """Write the CRCs recorded by :func:`_record_chunk_crcs` into the bag's chunk records."""
    files = sorted(bag.glob("*.mcap"))
    if len(files) != 1:
        raise DataError(f"{bag}: expected one .mcap file after writing, found {len(files)}")
    with files[0].open("r+b") as stream:
        summary = make_reader(stream).get_summary()
        offsets = sorted(c.chunk_start_offset for c in summary.chunk_indexes) if summary else []
        if len(offsets) != len(crcs):
            raise DataError(f"{files[0]}: {len(offsets)} chunks written but {len(crcs)} CRCs recorded")
        for offset, crc in zip(offsets, crcs):
            stream.seek(offset + _CHUNK_CRC_OFFSET)
            stream.write(struct.pack("<I", crc))
        stream.flush()
        os.fsync(stream.fileno())


def _set_mcap_zstd_level(writer: Writer, level: int) -> None:
    """Set the zstd level of rosbags' MCAP chunk compressor (its writer exposes no option)."""
    storage = writer.storage
    if not hasattr(storage, "compressor"):
        raise DataError("this rosbags version's MCAP writer has no compressor to configure")
    storage.compressor = partial(storage_mcap.zstd.compress, level=int(level))
