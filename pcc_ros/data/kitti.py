"""KITTI tracking and object readers, detector results and OXTS ego poses.

Every reader yields :class:`pcc_ros.types.Sample` objects in the Velodyne frame
(``frame_id = "velodyne"``, REP 103) with boxes already converted from KITTI's camera
convention (rectified camera frame, bottom centre, ``rotation_y``) to pcc_ros boxes
(geometric centre, size (l, w, h), yaw about +z) by :mod:`pcc_ros.data.kitti_format`,
so the conversion happens once, here.

Layouts (``ROOT`` may be the dataset directory holding ``training/`` or the split
directory itself):

- tracking: ``velodyne/SSSS/FFFFFF.bin``, ``label_02/SSSS.txt`` (frame, track id, type,
  ...), ``calib/SSSS.txt``, optional ``oxts/SSSS.txt`` (one OXTS line per frame).
- object: ``velodyne/FFFFFF.bin``, ``label_2/FFFFFF.txt``, ``calib/FFFFFF.txt``.
- detector results: one KITTI object-format file per frame with a 16th score column
  (what OpenPCDet writes), ``DIR/FFFFFF.txt`` or, for tracking, ``DIR/SSSS/FFFFFF.txt``; for
  tracking also AB3DMOT's one comma-separated file per sequence, ``DIR/SSSS.txt``
  (:func:`~pcc_ros.data.kitti_format.parse_ab3dmot_lines`).

Stamps: KITTI tracking has no per-scan timestamps. If a raw-style timestamp file exists
(``oxts/SSSS/timestamps.txt``, ``oxts/SSSS.timestamps.txt`` or
``velodyne/SSSS/timestamps.txt``; lines such as ``2011-09-26 13:02:25.964389445``), frame
``i`` takes line ``i``; otherwise frame ``i`` is stamped ``KITTI_EPOCH_NS + i * 0.1 s``
(the Velodyne's 10 Hz). Object frames are independent scans and are always stamped the
second way from their file index.

Poses: the standard KITTI OXTS -> pose conversion (Mercator projection with the scale of
the first frame's latitude, rotation Rz(yaw) Ry(pitch) Rx(roll), relative to the first
frame), giving ``odom <- imu``; ``Sample.pose`` is ``odom <- velodyne`` =
``odom <- imu @ inv(Tr_imu_to_velo)`` and ``Sample.extras["sensor_to_base"]`` holds
``base_link <- velodyne`` (base_link = the OXTS IMU), which the bag writer publishes on
``/tf_static``.
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Iterator
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from pcc_ros.data.kitti_format import (
    Calibration,
    camera_to_lidar_boxes,
    parse_ab3dmot_lines,
    parse_label_lines,
    read_text_lines,
)
from pcc_ros.errors import DataError
from pcc_ros.types import Boxes, Sample

log = logging.getLogger(__name__)

FRAME_ID = "velodyne"
FIELDS = ("x", "y", "z", "intensity")
#: Fixed epoch for synthetic stamps: 2011-09-26T00:00:00Z, the day most KITTI drives were recorded.
KITTI_EPOCH_NS = 1_316_995_200 * 1_000_000_000
#: Velodyne HDL-64E scan period (10 Hz).
FRAME_PERIOD_NS = 100_000_000
#: Classes of the KITTI devkits; anything else is kept with its name and counted.
KNOWN_CLASSES = frozenset(
    {"Car", "Van", "Truck", "Pedestrian", "Person_sitting", "Cyclist", "Tram", "Misc", "DontCare", "Person"}
)
_EARTH_RADIUS = 6378137.0  # WGS84 semi-major axis, as in the KITTI devkit


def read_float32_records(path: str | Path, columns: int) -> np.ndarray:
    """A headerless scan of ``columns`` float32 per point (KITTI ``.bin``, nuScenes ``.pcd.bin``).

    Raises :class:`DataError` for a missing file or one whose size is not a whole number of
    points (a truncated copy would otherwise shift every following point's fields).
    """
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise DataError(f"{path}: cannot read scan ({exc.strerror})") from exc
    step = 4 * columns
    if len(raw) % step:
        raise DataError(
            f"{path}: size {len(raw)} bytes is not a multiple of {step} ({columns} float32 per point); truncated?"
        )
    return np.frombuffer(raw, dtype=np.float32).reshape(-1, columns).copy()


def read_velodyne(path: str | Path) -> np.ndarray:
    """Read a KITTI ``.bin`` scan: ``(N, 4)`` float32 x, y, z, reflectance."""
    return read_float32_records(path, 4)


def _read_lines(path: Path) -> list[str]:
    return read_text_lines(path, "KITTI text")


def read_detections(path: str | Path, calib: Calibration) -> Boxes:
    """Detector results of one frame (KITTI object format + score column) as LiDAR-frame Boxes.

    A file without a score column reads with score 1. Raises :class:`DataError` with
    ``file:line`` for a malformed line.
    """
    path = Path(path)
    rows = parse_label_lines(_read_lines(path), tracking=False, source=str(path))
    return camera_to_lidar_boxes(rows, calib)


def read_oxts(path: str | Path) -> np.ndarray:
    """``(F, 30)`` float64 OXTS records (lat, lon, alt, roll, pitch, yaw, ...), one per line."""
    path = Path(path)
    rows = []
    for lineno, line in enumerate(_read_lines(path), 1):
        parts = line.split()
        if not parts:
            continue
        if len(parts) < 6:
            raise DataError(f"{path}:{lineno}: expected 30 OXTS values, got {len(parts)}")
        try:
            values = [float(v) for v in parts]
        except ValueError as exc:
            raise DataError(f"{path}:{lineno}: non-numeric OXTS value ({exc})") from exc
        if not np.all(np.isfinite(values[:6])):
            raise DataError(f"{path}:{lineno}: non-finite OXTS position / orientation")
        rows.append(values[:30] + [0.0] * (30 - min(len(values), 30)))
    return np.array(rows, dtype=np.float64).reshape(-1, 30)


def oxts_to_poses(oxts: np.ndarray) -> np.ndarray:
    """``(F, 4, 4)`` IMU poses relative to the first frame (odom <- imu), KITTI devkit style.

    Mercator projection with the scale of the first latitude, so the metric error stays
    small over a drive; rotation ``Rz(yaw) @ Ry(pitch) @ Rx(roll)``.
    """
    oxts = np.asarray(oxts, dtype=np.float64)
    n = len(oxts)
    if n == 0:
        return np.zeros((0, 4, 4))
    lat, lon, alt, roll, pitch, yaw = (oxts[:, i] for i in range(6))
    scale = np.cos(np.deg2rad(lat[0]))
    tx = scale * np.deg2rad(lon) * _EARTH_RADIUS
    ty = scale * _EARTH_RADIUS * np.log(np.tan(np.deg2rad(90.0 + lat) / 2.0))
    cr, sr, cp, sp, cy, sy = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw)
    poses = np.zeros((n, 4, 4))
    # R = Rz(yaw) @ Ry(pitch) @ Rx(roll), written out to stay vectorised over frames.
    poses[:, 0, 0] = cy * cp
    poses[:, 0, 1] = cy * sp * sr - sy * cr
    poses[:, 0, 2] = cy * sp * cr + sy * sr
    poses[:, 1, 0] = sy * cp
    poses[:, 1, 1] = sy * sp * sr + cy * cr
    poses[:, 1, 2] = sy * sp * cr - cy * sr
    poses[:, 2, 0] = -sp
    poses[:, 2, 1] = cp * sr
    poses[:, 2, 2] = cp * cr
    poses[:, 0, 3], poses[:, 1, 3], poses[:, 2, 3] = tx, ty, alt
    poses[:, 3, 3] = 1.0
    return np.linalg.inv(poses[0]) @ poses


def read_timestamps(path: str | Path) -> np.ndarray:
    """KITTI raw timestamp file (``YYYY-MM-DD HH:MM:SS.fffffffff`` per line, UTC) -> int64 ns."""
    path = Path(path)
    out = []
    for lineno, line in enumerate(_read_lines(path), 1):
        text = line.strip()
        if not text:
            continue
        try:
            day_time, _, frac = text.partition(".")
            base = datetime.strptime(day_time, "%Y-%m-%d %H:%M:%S").replace(tzinfo=timezone.utc)
            nanos = int((frac + "000000000")[:9]) if frac else 0
        except ValueError as exc:
            raise DataError(f"{path}:{lineno}: bad timestamp {text!r} ({exc})") from exc
        out.append(int(base.timestamp()) * 1_000_000_000 + nanos)
    return np.array(out, dtype=np.int64)


def split_dir(root: Path, split: str) -> Path:
    """The split folder of a KITTI root: ``root/split`` when it exists, else ``root`` itself
    when it holds ``velodyne/`` (the split directory was given); :class:`DataError` otherwise."""
    root = Path(root)
    if (root / split).is_dir():
        return root / split
    if (root / "velodyne").is_dir():
        return root
    raise DataError(f"{root}: neither {root / split} nor {root / 'velodyne'} exists (not a KITTI directory)")


def _count_unknown(labels: np.ndarray, counter: Counter) -> None:
    for name in set(labels.tolist()) - KNOWN_CLASSES:
        counter[name] += int(np.count_nonzero(labels == name))


class KittiTracking:
    """KITTI tracking dataset (also SynthCars output, which uses this layout).

    ``unknown_classes`` counts boxes whose class is not a KITTI class (kept with their name);
    ``missing_detections`` counts frames whose detector-result file is absent (read as empty).
    """

    def __init__(self, root: str | Path, split: str = "training") -> None:
        self.root = split_dir(Path(root), split)
        self.unknown_classes: Counter = Counter()
        self.missing_detections = 0

    def sequences(self) -> list[str]:
        return sorted(p.name for p in (self.root / "velodyne").iterdir() if p.is_dir())

    def scan_paths(self, sequence: str) -> list[Path]:
        """The sequence's scans in order; :class:`DataError` naming the first missing one when
        the numbering has a gap (never silently fewer frames)."""
        directory = self.root / "velodyne" / sequence
        if not directory.is_dir():
            raise DataError(f"{directory}: no such sequence (have {', '.join(self.sequences()) or 'none'})")
        scans = sorted(directory.glob("*.bin"))
        _check_no_gap(scans, directory)
        return scans

    def calibration(self, sequence: str) -> Calibration:
        return Calibration.read(self.root / "calib" / f"{sequence}.txt")

    def labels(self, sequence: str, calib: Calibration) -> dict[int, Boxes] | None:
        """Ground truth per frame index (LiDAR frame, track ids), or None without a label file."""
        path = self.root / "label_02" / f"{sequence}.txt"
        if not path.exists():
            return None
        rows = parse_label_lines(_read_lines(path), tracking=True, source=str(path))
        boxes = camera_to_lidar_boxes(rows, calib)
        _count_unknown(boxes.label, self.unknown_classes)
        order = np.argsort(rows.frame, kind="stable")
        frames, starts = np.unique(rows.frame[order], return_index=True)
        bounds = [*starts[1:].tolist(), len(order)]
        return {int(f): boxes[order[s:e]] for f, s, e in zip(frames, starts, bounds)}

    def poses(self, sequence: str, calib: Calibration) -> np.ndarray | None:
        """``(F, 4, 4)`` odom <- velodyne from ``oxts/SSSS.txt``, or None when absent."""
        path = self.root / "oxts" / f"{sequence}.txt"
        if not path.exists():
            return None
        if calib.Tr_imu_to_velo is None:
            raise DataError(f"{self.root / 'calib' / f'{sequence}.txt'}: lacks Tr_imu_to_velo, needed for {path}")
        return oxts_to_poses(read_oxts(path)) @ np.linalg.inv(_h(calib.Tr_imu_to_velo))

    def stamps(self, sequence: str, indices: np.ndarray) -> np.ndarray:
        for path in (
            self.root / "oxts" / sequence / "timestamps.txt",
            self.root / "oxts" / f"{sequence}.timestamps.txt",
            self.root / "velodyne" / sequence / "timestamps.txt",
        ):
            if path.exists():
                stamps = read_timestamps(path)
                if len(indices) and indices.max() >= len(stamps):
                    raise DataError(f"{path}: {len(stamps)} timestamps but frame {int(indices.max())} exists")
                return stamps[indices]
        return KITTI_EPOCH_NS + indices.astype(np.int64) * FRAME_PERIOD_NS

    def frames(
        self, sequence: str, detections_dir: str | Path | None = None, start: int = 0, stop: int | None = None
    ) -> Iterator[Sample]:
        """Frames of one sequence in order; ``start``/``stop`` select a slice of the scans."""
        before = self._counts()
        scans = self.scan_paths(sequence)[start:stop]
        indices = np.array([_frame_index(p) for p in scans], dtype=np.int64)
        calib = self.calibration(sequence)
        labels = self.labels(sequence, calib)
        poses = self.poses(sequence, calib)
        stamps = self.stamps(sequence, indices)
        per_sequence = self._ab3dmot_detections(detections_dir, sequence, calib)
        det_dir = None if per_sequence is not None else _detections_dir(detections_dir, sequence)
        if poses is not None and len(indices) and indices.max() >= len(poses):
            raise DataError(f"{self.root / 'oxts' / f'{sequence}.txt'}: {len(poses)} records, frame {indices.max()}")
        sensor_to_base = None if calib.Tr_imu_to_velo is None else np.linalg.inv(_h(calib.Tr_imu_to_velo))
        for scan, index, stamp in zip(scans, indices.tolist(), stamps.tolist()):
            extras = {"scan_path": str(scan)}
            if poses is not None and sensor_to_base is not None:
                extras["sensor_to_base"] = sensor_to_base
            yield Sample(
                stamp_ns=int(stamp),
                frame_id=FRAME_ID,
                points=read_velodyne(scan),
                fields=FIELDS,
                detections=(per_sequence.get(index, Boxes.empty()) if per_sequence is not None
                            else self._detections(det_dir, scan.stem, calib)),
                ground_truth=None if labels is None else labels.get(index, Boxes.empty()),
                pose=None if poses is None else poses[index],
                sequence=sequence,
                index=index,
                extras=extras,
            )
        self._report(sequence, before)

    @staticmethod
    def _ab3dmot_detections(detections_dir: str | Path | None, sequence: str,
                            calib: Calibration) -> dict[int, Boxes] | None:
        """Detections per frame index from AB3DMOT's one file per sequence, ``DIR/SSSS.txt`` (what its
        repository publishes for PointRCNN; a frame without a line has no detections), or None when
        ``DIR`` has no such file (per-frame files ``DIR[/SSSS]/FFFFFF.txt`` then)."""
        if detections_dir is None or (Path(detections_dir) / sequence).is_dir():
            return None
        path = Path(detections_dir) / f"{sequence}.txt"
        if not path.is_file():
            return None
        rows = parse_ab3dmot_lines(_read_lines(path), source=str(path))
        boxes = camera_to_lidar_boxes(rows, calib)
        return {int(f): boxes[rows.frame == f] for f in np.unique(rows.frame)}

    def _detections(self, det_dir: Path | None, stem: str, calib: Calibration) -> Boxes | None:
        if det_dir is None:
            return None
        path = det_dir / f"{stem}.txt"
        if not path.exists():
            self.missing_detections += 1
            return Boxes.empty()
        return read_detections(path, calib)

    def _counts(self) -> tuple[Counter, int]:
        return Counter(self.unknown_classes), self.missing_detections

    def _report(self, name: str, before: tuple[Counter, int]) -> None:
        """Log what this pass kept or skipped (counts since ``before``), never silently."""
        unknown = self.unknown_classes - before[0]
        if unknown:
            log.warning("%s: kept %d boxes of non-KITTI classes: %s", name, sum(unknown.values()), dict(unknown))
        missing = self.missing_detections - before[1]
        if missing:
            log.warning("%s: %d frames had no detector-result file (read as no detections)", name, missing)


class KittiObject(KittiTracking):
    """KITTI object detection dataset: independent scans ``velodyne/FFFFFF.bin``."""

    def sequences(self) -> list[str]:
        return [""]

    def frames(  # type: ignore[override]
        self, detections_dir: str | Path | None = None, start: int = 0, stop: int | None = None
    ) -> Iterator[Sample]:
        all_scans = sorted((self.root / "velodyne").glob("*.bin"))
        have = {p.stem for p in all_scans}
        lo, hi = (all_scans[0].stem, all_scans[-1].stem) if all_scans else ("", "")
        for folder in ("label_2", "calib"):  # a frame inside the scans' range with files but no scan
            orphans = sorted(p.stem for p in (self.root / folder).glob("*.txt")
                             if p.stem not in have and lo < p.stem < hi)
            if orphans:
                raise DataError(f"{self.root / 'velodyne' / (orphans[0] + '.bin')}: missing scan "
                                f"({folder}/{orphans[0]}.txt exists; {len(orphans)} missing "
                                f"between {lo}.bin and {hi}.bin)",
                                hint="restore the scans, or remove the files of the frames you dropped")
        scans = all_scans[start:stop]
        det_dir = None if detections_dir is None else Path(detections_dir)
        if det_dir is not None and not det_dir.is_dir():
            raise DataError(f"{det_dir}: detections directory does not exist")
        before = self._counts()
        for scan in scans:
            index = _frame_index(scan)
            calib = Calibration.read(self.root / "calib" / f"{scan.stem}.txt")
            label_path = self.root / "label_2" / f"{scan.stem}.txt"
            truth = None
            if label_path.exists():
                rows = parse_label_lines(_read_lines(label_path), tracking=False, source=str(label_path))
                truth = camera_to_lidar_boxes(rows, calib)
                _count_unknown(truth.label, self.unknown_classes)
            yield Sample(
                stamp_ns=KITTI_EPOCH_NS + index * FRAME_PERIOD_NS,
                frame_id=FRAME_ID,
                points=read_velodyne(scan),
                fields=FIELDS,
                detections=self._detections(det_dir, scan.stem, calib),
                ground_truth=truth,
                pose=None,
                sequence="",
                index=index,
                extras={"scan_path": str(scan)},
            )
        self._report(str(self.root), before)


def _h(matrix: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[: matrix.shape[0], : matrix.shape[1]] = matrix
    return out


def _check_no_gap(scans: list[Path], directory: Path) -> None:
    """:class:`DataError` naming the first missing ``FFFFFF.bin`` in a numbered sequence."""
    if not scans:
        return
    indices = np.array([_frame_index(p) for p in scans], dtype=np.int64)
    expected = np.arange(indices[0], indices[0] + len(indices))
    if not np.array_equal(indices, expected):
        first = int(expected[np.flatnonzero(indices != expected)[0]])
        width = len(scans[0].stem)
        total = int(indices[-1] - indices[0] + 1 - len(indices))
        raise DataError(f"{directory / f'{first:0{width}d}.bin'}: missing scan ({total} missing between "
                        f"{scans[0].name} and {scans[-1].name})",
                        hint="restore the scan; a sequence with a gap would silently lose frames")


def _frame_index(path: Path) -> int:
    try:
        return int(path.stem)
    except ValueError as exc:
        raise DataError(f"{path}: scan file name is not a frame number") from exc


def _detections_dir(detections_dir: str | Path | None, sequence: str) -> Path | None:
    """``DIR/SSSS`` when it exists (tracking layout), else ``DIR`` itself."""
    if detections_dir is None:
        return None
    base = Path(detections_dir)
    if (base / sequence).is_dir():
        return base / sequence
    if base.is_dir():
        return base
    raise DataError(f"{base}: detections directory does not exist")
