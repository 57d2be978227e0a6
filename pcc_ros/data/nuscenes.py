"""nuScenes reader for the official v1.0 JSON tables, without the devkit.

Reads ``ROOT/VERSION/{scene,sample,sample_data,sample_annotation,instance,category,
ego_pose,calibrated_sensor}.json`` (plus ``sensor.json`` when present) and yields one
:class:`pcc_ros.types.Sample` per LIDAR_TOP key frame, scene by scene in sample order:

- points: ``ROOT/<sample_data.filename>`` (``.pcd.bin``, 5 float32 per point: x, y, z,
  intensity 0-255, ring 0-31), fields ``("x", "y", "z", "intensity", "ring")``, frame
  ``LIDAR_TOP``;
- ground truth: ``sample_annotation`` boxes moved global -> ego -> LiDAR (quaternions are
  w, x, y, z), nuScenes size (w, l, h) reordered to pcc_ros (l, w, h), yaw about the
  LiDAR's +z; ``track_id`` = instance token; ``label`` = a KITTI-like class
  (:data:`CATEGORY_TO_LABEL`), the original nuScenes category in
  ``Sample.extras["category"]`` (same order as the boxes) and the annotators' point count
  in ``Sample.extras["num_lidar_pts"]``;
- stamp: ``sample_data.timestamp`` (microseconds) in ns;
- pose: ``odom <- LIDAR_TOP`` where odom is the nuScenes global (map) frame, i.e.
  ``ego_pose @ calibrated_sensor``; ``extras["sensor_to_base"]`` = ``calibrated_sensor``
  (base_link = the ego vehicle frame).
"""

from __future__ import annotations

import json
import logging
from collections import Counter, defaultdict
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from pcc_ros.data.kitti import read_float32_records
from pcc_ros.errors import DataError
from pcc_ros.geometry.rotations import quaternion_to_matrix, xyzw_from_wxyz
from pcc_ros.types import Boxes, Sample

log = logging.getLogger(__name__)

FRAME_ID = "LIDAR_TOP"
FIELDS = ("x", "y", "z", "intensity", "ring")
TABLES = (
    "scene", "sample", "sample_data", "sample_annotation", "instance", "category", "ego_pose", "calibrated_sensor"
)

#: nuScenes category (or its prefix, longest match wins) -> KITTI-like label.
CATEGORY_TO_LABEL: dict[str, str] = {
    "vehicle.car": "Car",
    "vehicle.emergency.police": "Car",
    "vehicle.emergency.ambulance": "Van",
    "vehicle.truck": "Truck",
    "vehicle.bus": "Bus",
    "vehicle.trailer": "Trailer",
    "vehicle.construction": "ConstructionVehicle",
    "vehicle.bicycle": "Cyclist",
    "vehicle.motorcycle": "Motorcyclist",
    "human.pedestrian": "Pedestrian",
    "movable_object": "Misc",
    "static_object": "Misc",
    "animal": "Misc",
}


def category_to_label(name: str) -> str:
    """KITTI-like label for a nuScenes category; unknown categories keep their own name."""
    parts = name.split(".")
    for k in range(len(parts), 0, -1):
        label = CATEGORY_TO_LABEL.get(".".join(parts[:k]))
        if label is not None:
            return label
    return name


def transform(record: dict, source: str) -> np.ndarray:
    """``4x4`` from a record with ``translation`` (3) and ``rotation`` (w, x, y, z)."""
    try:
        t = np.asarray(record["translation"], dtype=np.float64).reshape(3)
        q = np.asarray(record["rotation"], dtype=np.float64).reshape(4)
    except (KeyError, ValueError, TypeError) as exc:
        raise DataError(f"{source}: bad translation / rotation ({exc})") from exc
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(q)) and np.linalg.norm(q) > 0):
        raise DataError(f"{source}: non-finite or zero pose")
    out = np.eye(4)
    out[:3, :3] = quaternion_to_matrix(xyzw_from_wxyz(q))
    out[:3, 3] = t
    return out


def read_pcd_bin(path: str | Path) -> np.ndarray:
    """nuScenes ``.pcd.bin``: ``(N, 5)`` float32 x, y, z, intensity, ring."""
    return read_float32_records(path, 5)


class NuScenes:
    """nuScenes v1.0 tables under ``root/version`` (LIDAR_TOP key frames only)."""

    def __init__(self, root: str | Path, version: str = "v1.0-mini") -> None:
        self.root = Path(root)
        self.version = version
        table_dir = self.root / version
        if not table_dir.is_dir():
            raise DataError(f"{table_dir}: no nuScenes table directory (wrong --version?)")
        self.tables = {name: self._load(table_dir / f"{name}.json") for name in TABLES}
        sensor_path = table_dir / "sensor.json"
        self.tables["sensor"] = self._load(sensor_path) if sensor_path.exists() else []
        self._index()
        self.skipped: Counter = Counter()

    @staticmethod
    def _load(path: Path) -> list[dict]:
        try:
            data = json.loads(path.read_text())
        except OSError as exc:
            raise DataError(f"{path}: cannot read nuScenes table ({exc.strerror})") from exc
        except json.JSONDecodeError as exc:
            raise DataError(f"{path}:{exc.lineno}: invalid JSON ({exc.msg})") from exc
        if not isinstance(data, list):
            raise DataError(f"{path}: expected a JSON list of records")
        return data

    def _by_token(self, name: str) -> dict[str, dict]:
        try:
            return {r["token"]: r for r in self.tables[name]}
        except (KeyError, TypeError) as exc:
            raise DataError(f"{self.root / self.version / name}.json: record without a token") from exc

    def _index(self) -> None:
        self.samples = self._by_token("sample")
        self.ego_poses = self._by_token("ego_pose")
        self.calibrated = self._by_token("calibrated_sensor")
        self.instances = self._by_token("instance")
        self.categories = self._by_token("category")
        sensors = self._by_token("sensor")
        self.lidar_by_sample: dict[str, dict] = {}
        for sd in self.tables["sample_data"]:
            if not sd.get("is_key_frame", False) or not self._is_lidar_top(sd, sensors):
                continue
            self.lidar_by_sample[sd["sample_token"]] = sd
        self.annotations_by_sample: dict[str, list[dict]] = defaultdict(list)
        for ann in self.tables["sample_annotation"]:
            self.annotations_by_sample[ann["sample_token"]].append(ann)

    def _is_lidar_top(self, sd: dict, sensors: dict[str, dict]) -> bool:
        calib = self.calibrated.get(sd.get("calibrated_sensor_token", ""))
        if sensors and calib is not None and calib.get("sensor_token") in sensors:
            return sensors[calib["sensor_token"]].get("channel") == "LIDAR_TOP"
        return "LIDAR_TOP" in str(sd.get("filename", ""))  # sensor.json absent: the file path names the channel

    def scenes(self) -> list[str]:
        return [s["name"] for s in self.tables["scene"]]

    def frames(self, scene: str | None = None) -> Iterator[Sample]:
        """Key frames of ``scene`` (name or token; ``None`` = every scene) in sample order."""
        chosen = [s for s in self.tables["scene"] if scene is None or scene in (s.get("name"), s.get("token"))]
        if not chosen:
            raise DataError(f"{self.root / self.version}: no scene {scene!r} (have {', '.join(self.scenes())})")
        before = Counter(self.skipped)
        for rec in chosen:
            token, index = rec["first_sample_token"], 0
            while token:
                sample = self.samples.get(token)
                if sample is None:
                    where = self.root / self.version / "sample.json"
                    raise DataError(f"{where}: scene {rec['name']} links to missing sample {token}")
                sd = self.lidar_by_sample.get(token)
                if sd is None:
                    self.skipped["samples without a LIDAR_TOP key frame"] += 1
                else:
                    yield self._frame(rec["name"], index, sd)
                    index += 1
                token = sample.get("next", "")
        skipped = self.skipped - before
        if skipped:
            log.warning("nuScenes: skipped %s", dict(skipped))

    def _frame(self, scene: str, index: int, sd: dict) -> Sample:
        source = f"{self.root / self.version}/sample_data.json[{sd['token']}]"
        try:
            ego = transform(self.ego_poses[sd["ego_pose_token"]], f"ego_pose {sd['ego_pose_token']}")
            sensor = transform(self.calibrated[sd["calibrated_sensor_token"]], f"calibrated_sensor {source}")
        except KeyError as exc:
            raise DataError(f"{source}: references missing record {exc}") from exc
        lidar_from_global = np.linalg.inv(ego @ sensor)
        boxes, categories, counts = self._boxes(sd["sample_token"], lidar_from_global)
        return Sample(
            stamp_ns=int(sd["timestamp"]) * 1000,
            frame_id=FRAME_ID,
            points=read_pcd_bin(self.root / sd["filename"]),
            fields=FIELDS,
            detections=None,
            ground_truth=boxes,
            pose=ego @ sensor,
            sequence=scene,
            index=index,
            extras={"sensor_to_base": sensor, "category": categories, "num_lidar_pts": counts,
                    "sample_token": sd["sample_token"]},
        )

    def _boxes(self, sample_token: str, lidar_from_global: np.ndarray) -> tuple[Boxes, np.ndarray, np.ndarray]:
        anns = self.annotations_by_sample.get(sample_token, [])
        n = len(anns)
        if n == 0:
            return Boxes.empty(), np.empty(0, dtype=object), np.zeros(0, dtype=np.int64)
        try:
            centre = np.array([a["translation"] for a in anns], dtype=np.float64).reshape(n, 3)
            size_wlh = np.array([a["size"] for a in anns], dtype=np.float64).reshape(n, 3)
            rotation = quaternion_to_matrix(
                xyzw_from_wxyz(np.array([a["rotation"] for a in anns], dtype=np.float64).reshape(n, 4))
            )
            instance = [a["instance_token"] for a in anns]
            category = [self.categories[self.instances[t]["category_token"]]["name"] for t in instance]
        except (KeyError, ValueError, TypeError) as exc:
            raise DataError(
                f"{self.root / self.version}/sample_annotation.json: bad annotation of sample {sample_token} ({exc})"
            ) from exc
        centre_l = centre @ lidar_from_global[:3, :3].T + lidar_from_global[:3, 3]
        rot_l = lidar_from_global[:3, :3] @ rotation
        yaw = np.arctan2(rot_l[:, 1, 0], rot_l[:, 0, 0])
        labels = np.array([category_to_label(c) for c in category], dtype=object)
        boxes = Boxes(centre_l, size_wlh[:, [1, 0, 2]], yaw, labels, np.ones(n), np.array(instance, dtype=object))
        cats = np.empty(n, dtype=object)
        cats[:] = category
        counts = np.array([int(a.get("num_lidar_pts", -1)) for a in anns], dtype=np.int64)
        valid = boxes.valid_mask()
        if not valid.all():
            self.skipped["annotations with non-finite or non-positive size / pose"] += int(np.count_nonzero(~valid))
            return boxes[valid], cats[valid], counts[valid]
        return boxes, cats, counts
