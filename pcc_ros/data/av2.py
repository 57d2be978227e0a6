"""Argoverse 2 sensor-dataset logs (Apache Arrow feather tables), without the devkit.

A log directory ``LOG`` (its name is the log id) holds::

    LOG/sensors/lidar/<t_ns>.feather            x, y, z, intensity, laser_number, offset_ns per point
    LOG/annotations.feather                     timestamp_ns, track_uuid, category, length_m, width_m,
                                                height_m, qw, qx, qy, qz, tx_m, ty_m, tz_m, num_interior_pts
    LOG/calibration/egovehicle_SE3_sensor.feather   sensor_name, qw, qx, qy, qz, tx_m, ty_m, tz_m
    LOG/city_SE3_egovehicle.feather             timestamp_ns, qw, qx, qy, qz, tx_m, ty_m, tz_m

and a split directory (``train/``, ``val/``, ``test/``) holds logs. One
:class:`pcc_ros.types.Sample` per sweep, in time order:

- points: AV2 stores each sweep (both stacked 32-beam LiDARs) in the ``ego_vehicle`` frame;
  with ``frame="ego_vehicle"`` they are kept as recorded, with a sensor name (``up_lidar``, the
  default, or ``down_lidar``) the whole sweep is moved by ``inv(egovehicle_SE3_sensor)``. Fields ``x y z
  intensity ring time``: ``ring`` is ``laser_number`` (0-31 up, 32-63 down), ``time`` is
  ``offset_ns`` in seconds (float32, as the Velodyne ROS driver's per-point time);
- ground truth: every annotation whose ``timestamp_ns`` is a sweep's, the cuboid centre
  ``(tx, ty, tz)`` and rotation (quaternion ``w, x, y, z``) given in the ego frame, moved into
  the points' frame; size (length, width, height) as given; yaw = heading of the cuboid's x
  axis; ``track_id`` = ``track_uuid``; ``label`` = :func:`category_to_label` of ``category``
  (the category itself in ``extras["category"]``, the annotators' ``num_interior_pts`` in
  ``extras["num_interior_pts"]``);
- stamp: the sweep's file name (ns); pose: ``city <- points frame`` =
  ``city_SE3_egovehicle`` at the sweep's exact timestamp (the devkit's lookup) times the
  sensor's mounting; ``extras`` name the frames (``world_frame`` ``city``, ``base_frame``
  ``ego_vehicle``) and every other sensor of the calibration (``static_edges``), which the
  bag writer publishes on ``/tf`` and ``/tf_static``.

Annotations are accounted for: those at a stamp with no sweep, and those with a non-finite
or non-positive size / pose (left out), are counted and logged per pass.
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Iterator
from functools import cached_property
from pathlib import Path

import numpy as np

from pcc_ros.data.feather import read_columns
from pcc_ros.errors import DataError
from pcc_ros.geometry.rotations import quaternion_to_matrix, xyzw_from_wxyz
from pcc_ros.types import Boxes, Sample

log = logging.getLogger(__name__)

EGO_FRAME = "ego_vehicle"
CITY_FRAME = "city"
#: The default frame of the points: the upper LiDAR, because everything downstream takes the scan
#: frame's origin for the viewpoint (crop distances, the filter's free-space evidence); the ego
#: frame's origin is at the rear axle, below the sensors.
DEFAULT_FRAME = "up_lidar"
#: Largest angle (rad) between a chosen frame's +z and the ego vehicle's up axis: boxes are
#: yaw-only about +z, so a tilted or upside-down sensor frame (a camera, a flipped LiDAR) cannot
#: carry them.
MAX_FRAME_TILT = 0.35
FIELDS = ("x", "y", "z", "intensity", "ring", "time")
LIDAR_DIR = Path("sensors") / "lidar"
ANNOTATIONS = Path("annotations.feather")
CALIBRATION = Path("calibration") / "egovehicle_SE3_sensor.feather"
POSES = Path("city_SE3_egovehicle.feather")
LIDAR_COLUMNS = ("x", "y", "z", "intensity", "laser_number", "offset_ns")
SE3_COLUMNS = ("qw", "qx", "qy", "qz", "tx_m", "ty_m", "tz_m")
ANNOTATION_COLUMNS = ("timestamp_ns", "track_uuid", "category", "length_m", "width_m", "height_m",
                      *SE3_COLUMNS, "num_interior_pts")
CALIBRATION_COLUMNS = ("sensor_name", *SE3_COLUMNS)
POSE_COLUMNS = ("timestamp_ns", *SE3_COLUMNS)

#: The 30 AV2 sensor-dataset categories -> the package's KITTI-like labels (nuScenes maps to the
#: same ones): passenger vehicles of any size that a car completer fits are ``Car``; anything
#: else keeps a class the default ``classes: [Car, Van]`` leaves alone.
CATEGORY_TO_LABEL: dict[str, str] = {
    "REGULAR_VEHICLE": "Car",  # cars, vans, pickups, SUVs
    "LARGE_VEHICLE": "Truck",  # extended vans, fire trucks, RVs
    "BOX_TRUCK": "Truck",
    "TRUCK": "Truck",
    "TRUCK_CAB": "Truck",
    "BUS": "Bus",
    "ARTICULATED_BUS": "Bus",
    "SCHOOL_BUS": "Bus",
    "VEHICULAR_TRAILER": "Trailer",
    "MESSAGE_BOARD_TRAILER": "Trailer",
    "TRAFFIC_LIGHT_TRAILER": "Trailer",
    "RAILED_VEHICLE": "Tram",
    "PEDESTRIAN": "Pedestrian",
    "OFFICIAL_SIGNALER": "Pedestrian",
    "WHEELED_RIDER": "Pedestrian",  # a person on a scooter, skateboard ... (nuScenes: personal_mobility)
    "STROLLER": "Pedestrian",
    "WHEELCHAIR": "Pedestrian",
    "BICYCLE": "Cyclist",  # as nuScenes' vehicle.bicycle
    "BICYCLIST": "Cyclist",
    "MOTORCYCLE": "Motorcyclist",
    "MOTORCYCLIST": "Motorcyclist",
    "WHEELED_DEVICE": "Misc",
    "BOLLARD": "Misc",
    "CONSTRUCTION_CONE": "Misc",
    "CONSTRUCTION_BARREL": "Misc",
    "SIGN": "Misc",
    "STOP_SIGN": "Misc",
    "MOBILE_PEDESTRIAN_CROSSING_SIGN": "Misc",
    "ANIMAL": "Misc",
    "DOG": "Misc",
}

#: The same mapping as a node ``class_map`` value, for a detector that publishes AV2 category
#: names (docs/datasets.md): ``class_map: "<this>"`` makes them the package's classes.
CLASS_MAP = ", ".join(f"{category}:{label}" for category, label in CATEGORY_TO_LABEL.items())


def category_to_label(name: str) -> str:
    """The package label of an AV2 category; an unknown category keeps its own name."""
    return CATEGORY_TO_LABEL.get(str(name), str(name))


def se3_matrices(columns: dict[str, np.ndarray], source: Path) -> np.ndarray:
    """``(N, 4, 4)`` rigid transforms of AV2 ``qw qx qy qz tx_m ty_m tz_m`` columns; :class:`DataError`
    naming ``source`` and the first row with a non-finite or zero quaternion / translation."""
    q = np.stack([np.asarray(columns[k], dtype=np.float64) for k in ("qw", "qx", "qy", "qz")], axis=-1)
    t = np.stack([np.asarray(columns[k], dtype=np.float64) for k in ("tx_m", "ty_m", "tz_m")], axis=-1)
    bad = ~(np.isfinite(q).all(axis=1) & np.isfinite(t).all(axis=1) & (np.linalg.norm(q, axis=1) > 1e-9))
    if bad.any():
        row = int(np.flatnonzero(bad)[0])
        raise DataError(f"{source}: row {row}: non-finite or zero pose (q={q[row].tolist()}, t={t[row].tolist()})")
    out = np.zeros((len(q), 4, 4))
    out[:, :3, :3] = quaternion_to_matrix(xyzw_from_wxyz(q))
    out[:, :3, 3] = t
    out[:, 3, 3] = 1.0
    return out


def is_log(path: str | Path) -> bool:
    """A directory with ``sensors/lidar/`` (what makes an AV2 log; the tables are checked on reading)."""
    return (Path(path) / LIDAR_DIR).is_dir()


def log_dirs(path: str | Path) -> list[Path]:
    """``[path]`` for a log, its logs (sorted by name) for a split directory; :class:`DataError` otherwise."""
    path = Path(path)
    if is_log(path):
        return [path]
    logs = sorted(p for p in path.iterdir() if is_log(p)) if path.is_dir() else []
    if not logs:
        raise DataError(f"{path}: not an Argoverse 2 log (no {LIDAR_DIR}/) nor a split directory of logs",
                        hint="`pcc check-data` says what a layout needs")
    return logs


class Av2Log:
    """One AV2 sensor-dataset log; ``frame`` = a sensor of the calibration (``up_lidar``) or ``ego_vehicle``;
    ``labels=False`` reads no annotations (frames without ground truth).

    ``counts`` accumulates, over passes, the annotations placed on sweeps and those left out
    (at a stamp with no sweep, invalid geometry)."""

    def __init__(self, root: str | Path, frame: str = DEFAULT_FRAME, labels: bool = True) -> None:
        self.root = Path(root)
        self.labels = labels  # False: no ground truth read (the test split's logs have no annotations.feather)
        if not is_log(self.root):
            raise DataError(f"{self.root / LIDAR_DIR}: missing; {self.root} is not an Argoverse 2 log",
                            hint="`pcc check-data` says what a layout needs")
        self.log_id = self.root.name
        self.frame = frame
        self.counts: Counter = Counter()

    def sweep_paths(self) -> list[Path]:
        """The sweeps in time order; :class:`DataError` for a file not named ``<t_ns>.feather`` or none."""
        paths = list((self.root / LIDAR_DIR).glob("*.feather"))
        bad = [p.name for p in paths if not p.stem.isdigit()]
        if bad:
            raise DataError(f"{self.root / LIDAR_DIR / bad[0]}: a sweep file must be named <timestamp_ns>.feather")
        if not paths:
            raise DataError(f"{self.root / LIDAR_DIR}: no sweep (<timestamp_ns>.feather)")
        return sorted(paths, key=lambda p: int(p.stem))

    @cached_property
    def calibration(self) -> dict[str, np.ndarray]:
        """Sensor name -> ``ego_vehicle <- sensor`` (4x4)."""
        path = self.root / CALIBRATION
        columns = read_columns(path, CALIBRATION_COLUMNS, "sensor calibration", text=("sensor_name",))
        matrices = se3_matrices(columns, path)
        return {str(name): m for name, m in zip(columns["sensor_name"], matrices)}

    @cached_property
    def poses(self) -> tuple[np.ndarray, np.ndarray]:
        """``(stamps, city <- ego)`` sorted by stamp."""
        path = self.root / POSES
        columns = read_columns(path, POSE_COLUMNS, "ego poses")
        stamps = np.asarray(columns["timestamp_ns"], dtype=np.int64)
        order = np.argsort(stamps, kind="stable")
        return stamps[order], se3_matrices(columns, path)[order]

    def sensor_to_ego(self) -> np.ndarray:
        """``ego_vehicle <- frame`` (identity for the ego frame itself)."""
        if self.frame == EGO_FRAME:
            return np.eye(4)
        if self.frame not in self.calibration:
            raise DataError(f"{self.root / CALIBRATION}: no sensor {self.frame!r} "
                            f"(have {', '.join(sorted(self.calibration))}; or use {EGO_FRAME})")
        mount = self.calibration[self.frame]
        tilt = float(np.arccos(np.clip(mount[2, 2], -1.0, 1.0)))
        if tilt > MAX_FRAME_TILT:
            raise DataError(f"{self.root / CALIBRATION}: sensor {self.frame!r} is tilted {np.degrees(tilt):.0f} deg "
                            "from the vehicle's up axis; boxes are yaw-only about +z",
                            hint=f"use an upright frame: {DEFAULT_FRAME} or {EGO_FRAME}")
        return mount

    def pose_at(self, stamp: int) -> np.ndarray:
        """``city <- ego`` at exactly ``stamp`` (AV2 records a pose at every sweep time)."""
        stamps, matrices = self.poses
        i = int(np.searchsorted(stamps, stamp))
        if i == len(stamps) or stamps[i] != stamp:
            raise DataError(f"{self.root / POSES}: no pose at sweep time {stamp} "
                            f"({self.root / LIDAR_DIR / f'{stamp}.feather'})")
        return matrices[i]

    def _boxes(self, ego_to_frame: np.ndarray) -> tuple[np.ndarray, Boxes, dict[str, np.ndarray]]:
        """Every annotation in the points' frame (stamps, boxes, extras columns), invalid ones left out."""
        path = self.root / ANNOTATIONS
        if not path.is_file():
            raise DataError(f"{path}: missing annotations",
                            hint="a test-split log has none: convert it with --no-labels (no /ground_truth)")
        a = read_columns(path, ANNOTATION_COLUMNS, "annotations", text=("track_uuid", "category"))
        n = len(a["timestamp_ns"])
        q = np.stack([np.asarray(a[k], dtype=np.float64) for k in ("qw", "qx", "qy", "qz")], axis=-1).reshape(n, 4)
        finite_pose = np.isfinite(q).all(axis=1) & (np.linalg.norm(q, axis=1) > 1e-9)
        rotation = quaternion_to_matrix(xyzw_from_wxyz(np.where(finite_pose[:, None], q, [1.0, 0, 0, 0])))
        centre = np.stack([np.asarray(a[k], dtype=np.float64) for k in ("tx_m", "ty_m", "tz_m")], axis=-1)
        centre = centre.reshape(n, 3) @ ego_to_frame[:3, :3].T + ego_to_frame[:3, 3]
        rotation = ego_to_frame[:3, :3] @ rotation
        yaw = np.where(finite_pose, np.arctan2(rotation[:, 1, 0], rotation[:, 0, 0]), np.nan)
        size = np.stack([np.asarray(a[k], dtype=np.float64) for k in ("length_m", "width_m", "height_m")], axis=-1)
        names, which = np.unique(a["category"].astype(str), return_inverse=True)  # a few dozen names, not n
        labels = np.array([category_to_label(c) for c in names], dtype=object)[which.reshape(n)]
        boxes = Boxes(centre, size.reshape(n, 3), yaw, labels, np.ones(n),
                      np.array([str(u) for u in a["track_uuid"]], dtype=object).reshape(n))
        valid = boxes.valid_mask()
        self.counts["annotations invalid (left out)"] += int(np.count_nonzero(~valid))
        extras = {"category": a["category"][valid],
                  "num_interior_pts": np.asarray(a["num_interior_pts"], dtype=np.int64)[valid]}
        return np.asarray(a["timestamp_ns"], dtype=np.int64)[valid], boxes[valid], extras

    def frames(self, start: int = 0, stop: int | None = None) -> Iterator[Sample]:
        """The log's sweeps ``[start:stop]`` in time order (see the module docstring)."""
        before = Counter(self.counts)
        sweeps = self.sweep_paths()
        sweep_stamps = np.array([int(p.stem) for p in sweeps], dtype=np.int64)
        mount = self.sensor_to_ego()
        ego_to_frame = np.linalg.inv(mount)
        static_edges = [(EGO_FRAME, name, m) for name, m in sorted(self.calibration.items()) if name != self.frame]
        if self.labels:
            box_stamps, boxes, box_extras = self._boxes(ego_to_frame)
        else:
            box_stamps, boxes, box_extras = np.zeros(0, np.int64), Boxes.empty(), {
                "category": np.zeros(0, object), "num_interior_pts": np.zeros(0, np.int64)}
        order = np.argsort(box_stamps, kind="stable")
        box_stamps, boxes = box_stamps[order], boxes[order]
        box_extras = {k: v[order] for k, v in box_extras.items()}
        on_sweep = np.isin(box_stamps, sweep_stamps)
        self.counts["annotations at a stamp without a sweep (left out)"] += int(np.count_nonzero(~on_sweep))
        chosen = range(len(sweeps))[start:stop]
        for index in chosen:
            stamp = int(sweep_stamps[index])
            lo, hi = np.searchsorted(box_stamps, [stamp, stamp + 1])
            self.counts["annotations on converted sweeps"] += int(hi - lo)
            yield Sample(
                stamp_ns=stamp,
                frame_id=self.frame,
                points=self.read_sweep(sweeps[index], ego_to_frame),
                fields=FIELDS,
                detections=None,
                ground_truth=boxes[lo:hi] if self.labels else None,
                pose=self.pose_at(stamp) @ mount,
                sequence=self.log_id,
                index=index,
                extras={
                    **({} if self.frame == EGO_FRAME else {"sensor_to_base": mount}),
                    "world_frame": CITY_FRAME, "base_frame": EGO_FRAME, "static_edges": static_edges,
                    "category": box_extras["category"][lo:hi],
                    "num_interior_pts": box_extras["num_interior_pts"][lo:hi],
                    "scan_path": str(sweeps[index]),
                },
            )
        if len(chosen) < len(sweeps):
            outside = np.isin(box_stamps, sweep_stamps[chosen.start:chosen.stop], invert=True) & on_sweep
            self.counts["annotations on sweeps not converted (--first / --frames)"] += int(np.count_nonzero(outside))
        done = self.counts - before
        log.info("%s: %s", self.root, ", ".join(f"{n} {what}" for what, n in sorted(done.items())) or "no annotations")

    def read_sweep(self, path: Path, ego_to_frame: np.ndarray | None = None) -> np.ndarray:
        """``(N, 6)`` float32 ``x y z intensity ring time`` of one sweep, moved by ``ego_to_frame``."""
        c = read_columns(path, LIDAR_COLUMNS, "LiDAR sweep")
        xyz = np.stack([np.asarray(c[k], dtype=np.float64) for k in ("x", "y", "z")], axis=-1)
        if ego_to_frame is not None:
            xyz = xyz @ ego_to_frame[:3, :3].T + ego_to_frame[:3, 3]
        out = np.empty((len(xyz), len(FIELDS)), dtype=np.float32)
        out[:, :3] = xyz
        out[:, 3] = c["intensity"]
        out[:, 4] = c["laser_number"]
        out[:, 5] = np.asarray(c["offset_ns"], dtype=np.float64) * 1e-9
        return out
