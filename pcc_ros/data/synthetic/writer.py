"""SynthCars files in the KITTI tracking devkit layout (plus shapes and meta.json).

Layout under the output directory::

    training/velodyne/SSSS/FFFFFF.bin   float32 x, y, z, intensity
    training/label_02/SSSS.txt          KITTI tracking labels (camera frame, track ids)
    training/calib/SSSS.txt             calibration (exact LiDAR -> camera axis permutation)
    training/oxts/SSSS.txt              KITTI OXTS lines (30 values) of the ego pose
    training/poses/SSSS.txt             world <- velodyne 3x4 per frame (KITTI odometry style)
    detections/synthetic/SSSS/FFFFFF.txt  KITTI object lines + score column
    detections/synthetic/SSSS/FFFFFF.kind one line per detection, same order: its kind
                                        (true / confusion / ghost / far / misplaced) and the
                                        non-vehicle object a confusion sits on ("-" otherwise)
    shapes/SSSS/<track_id>.npy          float32 (M, 3) complete surface, canonical frame
    meta.json                           seed, parameters, splits, per-track info

Labels go through :mod:`pcc_ros.data.kitti_format` (the same code the readers use), so
they round-trip. The calibration maps LiDAR axes to camera axes by an exact permutation
(no rotation noise, no offset), so a box written and read back is the same box to the
printed precision (1e-6).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pcc_ros import files
from pcc_ros.data.kitti_format import Calibration, format_label_lines, lidar_to_camera_rows
from pcc_ros.errors import DataError
from pcc_ros.geometry.boxes import box_corners
from pcc_ros.types import Boxes

IMAGE_SIZE = (1242, 375)  # KITTI colour camera, used for the 2D boxes
EARTH_RADIUS = 6378137.0
ORIGIN_LAT_LON_ALT = (49.008644, 8.398104, 112.0)  # Karlsruhe, where KITTI drove


def calibration() -> Calibration:
    """KITTI-like intrinsics, identity rectification, LiDAR -> camera as a pure axis permutation."""
    p2 = np.array([[721.5377, 0.0, 609.5593, 0.0], [0.0, 721.5377, 172.854, 0.0], [0.0, 0.0, 1.0, 0.0]])
    velo_to_cam = np.array([[0.0, -1.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0], [1.0, 0.0, 0.0, 0.0]])
    imu_to_velo = np.c_[np.eye(3), np.zeros(3)]  # the pose reference (IMU) sits at the LiDAR
    return Calibration(P2=p2, R0_rect=np.eye(3), Tr_velo_to_cam=velo_to_cam, Tr_imu_to_velo=imu_to_velo, extra={})


def image_boxes(boxes: Boxes, calib: Calibration) -> np.ndarray:
    """``(N, 4)`` 2D boxes in the colour image; zeros for boxes not wholly in front of the camera."""
    corners = box_corners(boxes).reshape(-1, 3)
    cam = np.c_[corners, np.ones(len(corners))] @ calib.velo_to_rect.T
    uvw = cam @ calib.P2.T
    depth = uvw[:, 2].reshape(-1, 8)
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = (uvw[:, :2] / uvw[:, 2:3]).reshape(-1, 8, 2)
    out = np.zeros((len(boxes), 4))
    front = (depth > 0.5).all(axis=1)
    if front.any():
        w, h = IMAGE_SIZE
        lo, hi = uv[front].min(1), uv[front].max(1)
        box2d = np.c_[np.clip(lo[:, 0], 0, w - 1), np.clip(lo[:, 1], 0, h - 1),
                      np.clip(hi[:, 0], 0, w - 1), np.clip(hi[:, 1], 0, h - 1)]
        visible = (box2d[:, 2] > box2d[:, 0]) & (box2d[:, 3] > box2d[:, 1])
        box2d[~visible] = 0.0
        out[front] = box2d
    return out


def tracking_label_lines(boxes: Boxes, frame: int, occluded: np.ndarray, calib: Calibration) -> list[str]:
    """KITTI tracking lines of one frame (sensor-frame boxes with integer track ids)."""
    rows = lidar_to_camera_rows(boxes, calib, frame=frame, bbox=image_boxes(boxes, calib))
    rows.occluded = np.asarray(occluded, dtype=np.float64)
    return format_label_lines(rows, tracking=True, with_score=False)


def detection_lines(boxes: Boxes, calib: Calibration) -> list[str]:
    """KITTI object lines with a score column."""
    rows = lidar_to_camera_rows(boxes, calib, bbox=image_boxes(boxes, calib))
    return format_label_lines(rows, tracking=False, with_score=True)


#: File suffix of the per-frame detection kinds beside ``FFFFFF.txt``.
KIND_SUFFIX = ".kind"


def kind_lines(kind: np.ndarray, source: np.ndarray) -> list[str]:
    """One ``"<kind> <object>"`` line per detection, in the order of the detection file."""
    return [f"{k} {s}" for k, s in zip(kind, source)]


def read_kinds(path: Path, count: int) -> tuple[np.ndarray, np.ndarray] | None:
    """The kinds and objects of a frame's ``count`` detections, or None when the file is absent.
    A file that does not match the detections (line count, two words a line) raises DataError."""
    if not path.exists():
        return None
    try:
        rows = [line.split() for line in path.read_text().splitlines() if line.strip()]
    except OSError as exc:
        raise DataError(f"{path}: cannot read ({exc.strerror})") from exc
    if len(rows) != count or any(len(r) != 2 for r in rows):
        raise DataError(f"{path}: expected {count} lines of '<kind> <object>', got {len(rows)}")
    return np.array([r[0] for r in rows], dtype=object), np.array([r[1] for r in rows], dtype=object)


def oxts_lines(xy: np.ndarray, yaw: np.ndarray, z: float, dt: float) -> list[str]:
    """KITTI OXTS lines (lat, lon, alt, roll, pitch, yaw, velocities, ...), 30 values each.

    World x is east and y north; lat/lon invert the KITTI devkit's Mercator projection
    around :data:`ORIGIN_LAT_LON_ALT`, so ``devkit.convertOxtsToPose`` recovers ``xy``.
    """
    lat0, lon0, alt0 = ORIGIN_LAT_LON_ALT
    scale = np.cos(np.deg2rad(lat0))
    mx0 = scale * np.deg2rad(lon0) * EARTH_RADIUS
    my0 = scale * EARTH_RADIUS * np.log(np.tan(np.deg2rad(90 + lat0) / 2))
    lon = np.rad2deg((mx0 + xy[:, 0]) / (scale * EARTH_RADIUS))
    lat = np.rad2deg(2 * np.arctan(np.exp((my0 + xy[:, 1]) / (scale * EARTH_RADIUS)))) - 90
    vel = np.gradient(xy, dt, axis=0) if len(xy) > 1 else np.zeros_like(xy)
    c, s = np.cos(yaw), np.sin(yaw)
    vf, vl = c * vel[:, 0] + s * vel[:, 1], -s * vel[:, 0] + c * vel[:, 1]
    lines = []
    for i in range(len(xy)):  # one text line per frame
        values = [lat[i], lon[i], alt0 + z, 0.0, 0.0, yaw[i], vel[i, 1], vel[i, 0], vf[i], vl[i], 0.0]
        values += [0.0] * 12 + [0.05, 0.02]
        text = " ".join(f"{v:.12g}" for v in values)
        lines.append(f"{text} 4 10 5 5 6")
    return lines


def pose_lines(xy: np.ndarray, yaw: np.ndarray, z: float) -> list[str]:
    """World <- velodyne as 12 row-major values per frame."""
    lines = []
    for i in range(len(xy)):
        c, s = np.cos(yaw[i]), np.sin(yaw[i])
        m = [c, -s, 0.0, xy[i, 0], s, c, 0.0, xy[i, 1], 0.0, 0.0, 1.0, z]
        lines.append(" ".join(f"{v:.9e}" for v in m))
    return lines


def write_text(path: Path, lines: list[str]) -> None:
    """Atomic text write (temp file + rename) so an interrupted run leaves no half file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    files.write_text(path, "".join(f"{line}\n" for line in lines))


def write_bin(path: Path, points: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    files.write_bytes(path, np.ascontiguousarray(points, dtype=np.float32).tobytes())


def write_npy(path: Path, array: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    files.save_npy(path, np.ascontiguousarray(array, dtype=np.float32))
