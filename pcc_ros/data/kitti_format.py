"""KITTI text formats: calibration files and label lines, and the camera <-> LiDAR box maps.

KITTI stores 3D boxes in the rectified camera frame (x right, y down, z forward) by
their *bottom* centre, sizes as (h, w, l) and heading ``rotation_y`` about the camera
y axis. pcc_ros boxes (:class:`pcc_ros.types.Boxes`) live in the LiDAR frame by their
geometric centre with yaw about +z. The conversion happens here, once, for readers
(KITTI tracking/object, detector results) and for the SynthCars writer alike, so a
label written by one and read by the other round-trips exactly.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pcc_ros import files
from pcc_ros.errors import DataError
from pcc_ros.geometry.transforms import wrap_angle
from pcc_ros.types import Boxes

# Official object devkit spelling first, tracking devkit spelling second.
_KEY_ALIASES = {
    "R0_rect": ("R0_rect", "R_rect"),
    "Tr_velo_to_cam": ("Tr_velo_to_cam", "Tr_velo_cam"),
    "Tr_imu_to_velo": ("Tr_imu_to_velo", "Tr_imu_velo"),
}


def read_text_lines(path: str | Path, what: str = "text") -> list[str]:
    """Lines of a KITTI text file; :class:`DataError` naming the file for an unreadable or binary one."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise DataError(f"{path}: cannot read {what} file ({exc.strerror})") from exc
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = raw[: exc.start].count(b"\n") + 1
        raise DataError(f"{path}:{line}: not a {what} file (byte {exc.start} is not text)",
                        hint="the file is binary or damaged; restore it from the dataset") from None
    if "\0" in text:
        line = text[: text.index("\0")].count("\n") + 1
        raise DataError(f"{path}:{line}: not a {what} file (NUL byte)",
                        hint="the file is binary or damaged; restore it from the dataset")
    return text.splitlines()


def _is_rotation(matrix: np.ndarray, tol: float = 1e-2) -> bool:
    """``matrix`` is orthonormal with determinant +1 within ``tol`` (KITTI prints 7 digits)."""
    return bool(np.allclose(matrix @ matrix.T, np.eye(3), atol=tol) and abs(np.linalg.det(matrix) - 1.0) < tol)


def _homogeneous(matrix: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[: matrix.shape[0], : matrix.shape[1]] = matrix
    return out


@dataclass
class Calibration:
    """A KITTI calibration: camera projections, rectification and LiDAR -> camera."""

    P2: np.ndarray  # (3, 4)
    R0_rect: np.ndarray  # (3, 3)
    Tr_velo_to_cam: np.ndarray  # (3, 4)
    Tr_imu_to_velo: np.ndarray | None = None  # (3, 4)
    extra: dict | None = None  # other keys verbatim (P0, P1, P3, Tr_cam_to_road ...)

    @classmethod
    def read(cls, path: str | Path) -> Calibration:
        path = Path(path)
        values: dict[str, np.ndarray] = {}
        for lineno, line in enumerate(read_text_lines(path, "calibration"), 1):
            parts = line.split()
            if not parts:
                continue
            key = parts[0].rstrip(":")
            try:
                values[key] = np.array([float(v) for v in parts[1:]], dtype=np.float64)
            except ValueError as exc:
                raise DataError(f"{path}:{lineno}: non-numeric calibration value ({exc})") from exc
            if not np.isfinite(values[key]).all():
                raise DataError(f"{path}:{lineno}: non-finite value in {key}",
                                hint="the calibration file is damaged; restore it from the dataset")

        def get(name: str, shape: tuple[int, int], required: bool = True) -> np.ndarray | None:
            for alias in _KEY_ALIASES.get(name, (name,)):
                if alias in values:
                    v = values[alias]
                    if v.size != shape[0] * shape[1]:
                        raise DataError(f"{path}: key {alias} has {v.size} values, expected {shape[0] * shape[1]}")
                    return v.reshape(shape)
            if required:
                raise DataError(f"{path}: calibration lacks {' / '.join(_KEY_ALIASES.get(name, (name,)))}")
            return None

        known = {a for aliases in _KEY_ALIASES.values() for a in aliases} | {"P2"}
        calib = cls(
            P2=get("P2", (3, 4)),
            R0_rect=get("R0_rect", (3, 3)),
            Tr_velo_to_cam=get("Tr_velo_to_cam", (3, 4)),
            Tr_imu_to_velo=get("Tr_imu_to_velo", (3, 4), required=False),
            extra={k: v for k, v in values.items() if k not in known},
        )
        for name in ("R0_rect", "Tr_velo_to_cam", "Tr_imu_to_velo"):
            matrix = getattr(calib, name)
            if matrix is not None and not _is_rotation(matrix[:3, :3]):
                raise DataError(
                    f"{path}: {name} is not a rotation (det {np.linalg.det(matrix[:3, :3]):.3g}; singular or scaled)",
                    hint="the calibration file is damaged; restore it from the dataset",
                )
        return calib

    def write(self, path: str | Path) -> None:
        """Write in the object devkit spelling (readers accept both)."""
        lines = []
        extra = dict(self.extra or {})
        for key in ("P0", "P1"):
            lines.append((key, extra.pop(key, self.P2.ravel())))
        lines.append(("P2", self.P2.ravel()))
        lines.append(("P3", extra.pop("P3", self.P2.ravel())))
        lines.append(("R0_rect", self.R0_rect.ravel()))
        lines.append(("Tr_velo_to_cam", self.Tr_velo_to_cam.ravel()))
        if self.Tr_imu_to_velo is not None:
            lines.append(("Tr_imu_to_velo", self.Tr_imu_to_velo.ravel()))
        lines.extend(extra.items())

        files.write_text(path, "".join(f"{k}: {' '.join(f'{v:.12e}' for v in vals)}\n" for k, vals in lines))

    @property
    def velo_to_rect(self) -> np.ndarray:
        """``4x4`` LiDAR -> rectified camera."""
        return _homogeneous(self.R0_rect) @ _homogeneous(self.Tr_velo_to_cam)

    @property
    def rect_to_velo(self) -> np.ndarray:
        """``4x4`` rectified camera -> LiDAR."""
        return np.linalg.inv(self.velo_to_rect)


@dataclass
class LabelRows:
    """Parsed KITTI label lines (object or tracking), struct of arrays in camera frame."""

    type: np.ndarray  # (N,) object array of class names, "DontCare" kept verbatim
    truncated: np.ndarray
    occluded: np.ndarray
    alpha: np.ndarray
    bbox: np.ndarray  # (N, 4)
    hwl: np.ndarray  # (N, 3) height, width, length
    location: np.ndarray  # (N, 3) bottom centre, rectified camera frame
    rotation_y: np.ndarray
    score: np.ndarray  # (N,) 1.0 when the file has no score column
    frame: np.ndarray  # (N,) int frame index (tracking), -1 for object files
    track_id: np.ndarray  # (N,) int track id (tracking), -1 when absent / DontCare

    def __len__(self) -> int:
        return len(self.type)

    def __getitem__(self, index) -> LabelRows:
        return LabelRows(**{k: v[index] for k, v in self.__dict__.items()})


def parse_label_lines(lines: list[str], tracking: bool, source: str = "<labels>") -> LabelRows:
    """Parse KITTI object (15/16 columns) or tracking (17/18 columns) label lines.

    Raises :class:`DataError` naming ``source`` and the line for a malformed line.
    """
    head = 2 if tracking else 0
    types, numbers, frames, tracks, scores = [], [], [], [], []
    for lineno, line in enumerate(lines, 1):
        parts = line.split()
        if not parts:
            continue
        if len(parts) not in (head + 15, head + 16):
            raise DataError(
                f"{source}:{lineno}: expected {head + 15} or {head + 16} columns, got {len(parts)}"
            )
        try:
            if tracking:
                frames.append(int(parts[0]))
                tracks.append(int(parts[1]))
            values = [float(v) for v in parts[head + 1 : head + 15]]
            scores.append(float(parts[head + 15]) if len(parts) == head + 16 else 1.0)
        except ValueError as exc:
            raise DataError(f"{source}:{lineno}: non-numeric field ({exc})") from exc
        if not np.all(np.isfinite(values)):
            raise DataError(f"{source}:{lineno}: non-finite value in label")
        if not np.isfinite(scores[-1]):
            raise DataError(f"{source}:{lineno}: non-finite score {parts[head + 15]!r}",
                            hint="fix or drop that line of the detector output")
        if parts[head] != "DontCare" and not min(values[7:10]) > 0:
            raise DataError(f"{source}:{lineno}: {parts[head]} box has size h, w, l = {values[7:10]} (must be > 0)",
                            hint="fix or drop that line; only DontCare rows may have no 3D extent")
        types.append(parts[head])
        numbers.append(values)
    n = len(types)
    num = np.array(numbers, dtype=np.float64).reshape(n, 14)
    type_array = np.empty(n, dtype=object)
    type_array[:] = types
    return LabelRows(
        type=type_array,
        truncated=num[:, 0],
        occluded=num[:, 1],
        alpha=num[:, 2],
        bbox=num[:, 3:7],
        hwl=num[:, 7:10],
        location=num[:, 10:13],
        rotation_y=num[:, 13],
        score=np.array(scores, dtype=np.float64),
        frame=np.array(frames if tracking else [-1] * n, dtype=np.int64),
        track_id=np.array(tracks if tracking else [-1] * n, dtype=np.int64),
    )


#: AB3DMOT's type ids in its KITTI detection files (``data/KITTI/detection/pointrcnn_*``).
AB3DMOT_TYPES = {"1": "Pedestrian", "2": "Car", "3": "Cyclist"}


def parse_ab3dmot_lines(lines: list[str], source: str = "<detections>") -> LabelRows:
    """AB3DMOT's per-sequence detection file (comma-separated ``frame, type id, x1, y1, x2, y2,
    score, h, w, l, x, y, z, rot_y, alpha``, the PointRCNN results its repository publishes) as
    label rows with ``frame`` set: each line is rewritten as a KITTI object line with a score
    column and parsed by :func:`parse_label_lines`, so both formats share one set of checks and
    an error names the file's own line."""
    frames, kitti_lines = [], []
    for lineno, line in enumerate(lines, 1):
        parts = [p.strip() for p in line.split(",")] if line.strip() else []
        if not parts:
            kitti_lines.append("")  # keeps the line numbers of the errors the file's own
            continue
        if len(parts) != 15:
            raise DataError(f"{source}:{lineno}: expected 15 comma-separated AB3DMOT columns (frame, type, 2D box, "
                            f"score, h w l x y z rot_y, alpha), got {len(parts)}")
        try:
            frames.append(int(parts[0]))
            kind = AB3DMOT_TYPES.get(str(int(float(parts[1]))), parts[1])
        except ValueError as exc:
            raise DataError(f"{source}:{lineno}: non-numeric frame or type ({exc})") from exc
        kitti_lines.append(" ".join([kind, "0", "0", parts[14], *parts[2:6], *parts[7:14], parts[6]]))
    rows = parse_label_lines(kitti_lines, tracking=False, source=source)
    rows.frame = np.array(frames, dtype=np.int64)
    return rows


def camera_to_lidar_boxes(rows: LabelRows, calib: Calibration) -> Boxes:
    """Camera-frame label rows -> LiDAR-frame :class:`Boxes` (geometric centre, yaw about +z)."""
    n = len(rows)
    bottom = np.c_[rows.location, np.ones(n)] @ calib.rect_to_velo.T
    center = bottom[:, :3].copy()
    height = rows.hwl[:, 0]
    center[:, 2] += height / 2.0
    size = np.stack([rows.hwl[:, 2], rows.hwl[:, 1], height], axis=1)
    yaw = wrap_angle(-rows.rotation_y - np.pi / 2.0)
    track = np.array([str(t) if t >= 0 else "" for t in rows.track_id], dtype=object)
    return Boxes(center, size, yaw, rows.type.copy(), rows.score.copy(), track)


def lidar_to_camera_rows(
    boxes: Boxes, calib: Calibration, frame: int = -1, bbox: np.ndarray | None = None
) -> LabelRows:
    """Inverse of :func:`camera_to_lidar_boxes` (2D boxes default to zeros, alpha derived)."""
    n = len(boxes)
    bottom = boxes.center.copy()
    bottom[:, 2] -= boxes.size[:, 2] / 2.0
    location = (np.c_[bottom, np.ones(n)] @ calib.velo_to_rect.T)[:, :3]
    rotation_y = wrap_angle(-boxes.yaw - np.pi / 2.0)
    alpha = wrap_angle(rotation_y - np.arctan2(location[:, 0], location[:, 2]))
    track = np.array([int(t) if str(t).lstrip("-").isdigit() else -1 for t in boxes.track_id], dtype=np.int64)
    return LabelRows(
        type=boxes.label.copy(),
        truncated=np.zeros(n),
        occluded=np.zeros(n),
        alpha=alpha,
        bbox=np.zeros((n, 4)) if bbox is None else np.asarray(bbox, dtype=np.float64),
        hwl=np.stack([boxes.size[:, 2], boxes.size[:, 1], boxes.size[:, 0]], axis=1),
        location=location,
        rotation_y=rotation_y,
        score=boxes.score.copy(),
        frame=np.full(n, frame, dtype=np.int64),
        track_id=track,
    )


def format_label_lines(rows: LabelRows, tracking: bool, with_score: bool) -> list[str]:
    """KITTI label lines (object or tracking layout), optionally with a score column."""
    lines = []
    for i in range(len(rows)):  # one line of text per box: a loop over boxes, not points
        values = [
            rows.truncated[i], rows.occluded[i], rows.alpha[i], *rows.bbox[i],
            *rows.hwl[i], *rows.location[i], rows.rotation_y[i],
        ]
        text = " ".join(f"{v:.6f}" for v in values)
        prefix = f"{rows.frame[i]} {rows.track_id[i]} " if tracking else ""
        suffix = f" {rows.score[i]:.6f}" if with_score else ""
        lines.append(f"{prefix}{rows.type[i]} {text}{suffix}")
    return lines
