"""A small Argoverse 2 sensor-dataset log written by the tests, in the exact feather schema.

Geometry is real-valued and constructed, not copied: the ego vehicle drives along a curve in
the city frame; three tracks (a car driving alongside, a parked car, a pedestrian) and a
bollard are cuboids in the city frame, written in the ego frame of each sweep as AV2 stores
them; each sweep's points are the tracks' box surfaces plus a ground patch, in the ego frame
(x, y, z float16, as AV2's files are). Column types follow the released files: intensity and
laser_number uint8, offset_ns uint32, annotation floats float32, num_interior_pts uint32.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.feather as feather
from scipy.spatial.transform import Rotation
from shapes import box_surface

T0 = 315_967_000_000_000_000  # AV2-like epoch stamps (ns)
PERIOD = 100_000_000

#: track uuid -> (category, size l w h, city pose at t=0 (x, y, yaw), velocity (m/s along its heading))
TRACKS = {
    "4c1e3a0e-0000-4000-8000-00000000car1": ("REGULAR_VEHICLE", (4.6, 1.9, 1.6), (12.0, 4.0, 0.1), 6.0),
    "4c1e3a0e-0000-4000-8000-00000000car2": ("REGULAR_VEHICLE", (4.2, 1.8, 1.5), (20.0, -5.0, 1.4), 0.0),
    "4c1e3a0e-0000-4000-8000-0000000000ped": ("PEDESTRIAN", (0.6, 0.6, 1.8), (8.0, -3.0, -1.2), 1.2),
    "4c1e3a0e-0000-4000-8000-00000bollard1": ("BOLLARD", (0.3, 0.3, 1.0), (15.0, 6.0, 0.0), 0.0),
}
SENSORS = {  # sensor -> (ego <- sensor): rotation (xyz Euler, rad) and translation (m)
    "up_lidar": ((0.0, 0.0, 0.02), (1.35, 0.0, 1.64)),
    "down_lidar": ((np.pi, 0.0, 0.03), (1.35, 0.0, 1.59)),
    "ring_front_center": ((-np.pi / 2, 0.0, -np.pi / 2), (1.63, 0.0, 1.42)),
}


def _matrix(rotation: Rotation, t) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = rotation.as_matrix()
    m[:3, 3] = t
    return m


def _wxyz_t(m: np.ndarray) -> dict[str, float]:
    x, y, z, w = Rotation.from_matrix(m[:3, :3]).as_quat()
    return {"qw": w, "qx": x, "qy": y, "qz": z, "tx_m": m[0, 3], "ty_m": m[1, 3], "tz_m": m[2, 3]}


@dataclass
class Av2Truth:
    """What the fixture wrote, for the tests' expectations."""

    root: Path
    stamps: list[int]
    ego_poses: dict[int, np.ndarray] = field(default_factory=dict)  # city <- ego per sweep
    calibration: dict[str, np.ndarray] = field(default_factory=dict)  # ego <- sensor
    annotation_count: int = 0
    off_sweep_annotations: int = 0


def write_log(root: Path, sweeps: int = 4, seed: int = 0, start: int = T0, points_per_box: int = 500) -> Av2Truth:
    """Write one AV2 log at ``root`` (the directory's name is the log id)."""
    rng = np.random.default_rng(seed)
    (root / "sensors" / "lidar").mkdir(parents=True)
    (root / "calibration").mkdir()
    truth = Av2Truth(root, [start + k * PERIOD for k in range(sweeps)])
    calib_rows = []
    for name, (euler, t) in SENSORS.items():
        m = _matrix(Rotation.from_euler("xyz", euler), t)
        truth.calibration[name] = m
        calib_rows.append({"sensor_name": name, **_wxyz_t(m)})
    feather.write_feather(pa.Table.from_pylist(calib_rows), root / "calibration" / "egovehicle_SE3_sensor.feather")

    pose_rows, ann_rows = [], []
    for k, stamp in enumerate(truth.stamps):
        s = k * PERIOD * 1e-9
        ego = _matrix(Rotation.from_euler("xyz", (0.01, -0.02, 0.3 + 0.05 * s)),
                      (100.0 + 8.0 * s, 50.0 + 0.5 * s, 3.0))
        truth.ego_poses[stamp] = ego
        pose_rows.append({"timestamp_ns": stamp, **_wxyz_t(ego)})
        pose_rows.append({"timestamp_ns": stamp + PERIOD // 3, **_wxyz_t(ego)})  # camera-time poses as well
        ego_from_city = np.linalg.inv(ego)
        clouds, rings = [], []
        for uuid, (category, size, (x, y, yaw), speed) in TRACKS.items():
            city = _matrix(Rotation.from_euler("z", yaw),
                           (ego[0, 3] + x + speed * s * np.cos(yaw), ego[1, 3] + y + speed * s * np.sin(yaw),
                            ego[2, 3] - 1.6 + size[2] / 2))
            box = ego_from_city @ city  # cuboid pose in the ego frame, as annotations.feather holds it
            surface = box_surface(rng, points_per_box, 0.46 * np.asarray(size))
            clouds.append(surface @ box[:3, :3].T + box[:3, 3])
            rings.append(rng.integers(0, 64, len(surface)))
            ann_rows.append({"timestamp_ns": stamp, "track_uuid": uuid, "category": category,
                             "length_m": size[0], "width_m": size[1], "height_m": size[2], **_wxyz_t(box),
                             "num_interior_pts": len(surface)})
        ground = np.column_stack([rng.uniform(-30, 30, (3000, 2)), np.full(3000, -1.6) + rng.normal(0, 0.02, 3000)])
        clouds.append(ground)
        rings.append(rng.integers(0, 64, len(ground)))
        xyz = np.concatenate(clouds).astype(np.float16)
        n = len(xyz)
        sweep = pa.table({
            "x": pa.array(xyz[:, 0]), "y": pa.array(xyz[:, 1]), "z": pa.array(xyz[:, 2]),
            "intensity": pa.array(rng.integers(0, 256, n).astype(np.uint8)),
            "laser_number": pa.array(np.concatenate(rings).astype(np.uint8)),
            "offset_ns": pa.array(rng.integers(0, PERIOD, n).astype(np.uint32)),
        })
        feather.write_feather(sweep, root / "sensors" / "lidar" / f"{stamp}.feather")
    # one annotation at a time with no sweep (a real log's annotations all sit on sweeps; the
    # reader must still account for such a row)
    ann_rows.append({**ann_rows[0], "timestamp_ns": truth.stamps[-1] + PERIOD})
    truth.annotation_count, truth.off_sweep_annotations = len(ann_rows), 1
    floats = ("length_m", "width_m", "height_m", "qw", "qx", "qy", "qz", "tx_m", "ty_m", "tz_m")
    table = pa.table({
        "timestamp_ns": pa.array([r["timestamp_ns"] for r in ann_rows], pa.int64()),
        "track_uuid": pa.array([r["track_uuid"] for r in ann_rows], pa.string()),
        # dictionary-encoded, as pandas writes a Categorical column; the reader takes plain strings alike
        "category": pa.array([r["category"] for r in ann_rows], pa.string()).dictionary_encode(),
        **{c: pa.array([r[c] for r in ann_rows], pa.float32()) for c in floats},
        "num_interior_pts": pa.array([r["num_interior_pts"] for r in ann_rows], pa.uint32()),
    })
    feather.write_feather(table, root / "annotations.feather")
    poses = pa.table({"timestamp_ns": pa.array([r["timestamp_ns"] for r in pose_rows], pa.int64()),
                      **{c: pa.array([r[c] for r in pose_rows], pa.float64()) for c in
                         ("qw", "qx", "qy", "qz", "tx_m", "ty_m", "tz_m")}})
    feather.write_feather(poses, root / "city_SE3_egovehicle.feather")
    return truth


def read_table(path: Path) -> dict[str, np.ndarray]:
    """Every column of a feather file as numpy (the tests' independent view of the tables)."""
    table = feather.read_table(path)
    return {name: np.asarray(table.column(name).to_pylist()) for name in table.column_names}
