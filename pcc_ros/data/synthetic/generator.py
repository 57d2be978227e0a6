"""SynthCars generation: streets -> simulated scans, labels, detections and shapes on disk.

Randomness is split into independent streams keyed by (seed, split, sequence[, frame])
with numpy ``SeedSequence`` spawn keys, so (1) a sequence is the same whether it is
generated alone, first or last, which makes an interrupted run resumable sequence by
sequence, and (2) train and test sequences draw their vehicle shapes from different
streams: the two shape sets are disjoint.
"""

from __future__ import annotations

import json
import logging
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from pcc_ros.data.synthetic import writer
from pcc_ros.data.synthetic.detector import DetectorParams, detect
from pcc_ros.data.synthetic.lidar import Scan, Sensor, cast
from pcc_ros.data.synthetic.reading import load_families, load_shape  # noqa: F401  (the package's names)
from pcc_ros.data.synthetic.scene import (
    KIND_CLUTTER,
    KIND_GROUND,
    KIND_PEDESTRIAN,
    KIND_STRUCTURE,
    KIND_VEHICLE,
    SceneParams,
    Street,
    build_street,
)
from pcc_ros.data.synthetic.vehicles import LABELS, canonical_shape
from pcc_ros.errors import ConfigError, DataError
from pcc_ros.geometry.transforms import wrap_angle
from pcc_ros.types import Boxes

log = logging.getLogger(__name__)

FORMAT_VERSION = 1
SPLIT_CODES = {"train": 1, "test": 2}
STREET_STREAM, SHAPES_STREAM, FRAME_STREAM = 0, 1, 2


@dataclass(frozen=True)
class LabelParams:
    label_range: float = 80.0  # metres; farther objects are not labelled
    min_points: int = 1  # objects with fewer LiDAR returns are not labelled


@dataclass
class FrameResult:
    """Everything simulated for one frame (sensor frame)."""

    scan: Scan
    gt: Boxes  # labelled objects (Car / Van / Pedestrian) with track ids
    gt_points: np.ndarray  # (K,) returns on each labelled object
    occluded: np.ndarray  # (K,) KITTI occlusion level 0..2
    detections: Boxes
    detection_kind: np.ndarray  # (D,) "true" or a false-positive kind (detector.FALSE_KINDS)
    detection_source: np.ndarray  # (D,) the non-vehicle object a confusion sits on, "-" otherwise

    @property
    def detection_true(self) -> np.ndarray:
        """``(D,)`` bool: the detection is on a real car (kind ``"true"``)."""
        return self.detection_kind == "true"


def seeded_rng(seed: int, *key: int) -> np.random.Generator:
    """The random stream of ``key`` (split, sequence, stream kind, ...) under ``seed``: independent per key."""
    return np.random.default_rng(np.random.SeedSequence(entropy=seed, spawn_key=key))


def splits_for(sequences: int, test_fraction: float) -> dict[str, list[str]]:
    """The last ``round(S * test_fraction)`` sequences are test (at least one when S >= 2)."""
    n_test = round(sequences * test_fraction)
    if sequences >= 2 and test_fraction > 0:
        n_test = max(n_test, 1)
    n_test = min(n_test, sequences - 1) if sequences >= 2 else 0
    names = [f"{i:04d}" for i in range(sequences)]
    return {"train": names[: sequences - n_test], "test": names[sequences - n_test :]}


def build_sequence(seed: int, index: int, frames: int, split: str, scene: SceneParams | None = None) -> Street:
    """The street of sequence ``index`` (identical on every call for the same arguments)."""
    return build_street(frames, scene or SceneParams(), seeded_rng(seed, SPLIT_CODES[split], index, STREET_STREAM))


def sensor_pose(street: Street, frame: int, sensor: Sensor) -> tuple[np.ndarray, float]:
    """World position of the LiDAR and the ego heading at a frame."""
    return np.r_[street.ego_xy[frame], sensor.mount_height], float(street.ego_yaw[frame])


def to_sensor(points_xy: np.ndarray, z: np.ndarray, origin: np.ndarray, yaw: float) -> np.ndarray:
    """World ``(N, 2)`` + heights -> sensor-frame ``(N, 3)``."""
    c, s = np.cos(yaw), np.sin(yaw)
    d = points_xy - origin[:2]
    return np.c_[c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], z - origin[2]]


def expected_points(boxes: Boxes, sensor: Sensor) -> np.ndarray:
    """Returns an unoccluded box would get: silhouette area over the beam footprint at its range."""
    r = np.maximum(np.linalg.norm(boxes.center, axis=1), 1.0)
    beta = np.arctan2(boxes.center[:, 1], boxes.center[:, 0]) - boxes.yaw
    area = boxes.size[:, 2] * (boxes.size[:, 0] * np.abs(np.sin(beta)) + boxes.size[:, 1] * np.abs(np.cos(beta)))
    d_az = np.deg2rad(360.0 / len(sensor.azimuths))
    table = sensor.model.elevations_deg
    d_el = np.deg2rad((table[-1] - table[0]) / (len(table) - 1))
    return area / (r**2 * d_az * d_el) * (1 - sensor.dropout)


def simulate_frame(
    street: Street,
    frame: int,
    sensor: Sensor,
    rng: np.random.Generator,
    detector: DetectorParams | None = None,
    labels: LabelParams | None = None,
) -> FrameResult:
    """Cast one revolution, label the visible objects and run the simulated detector."""
    detector, labels = detector or DetectorParams(), labels or LabelParams()
    origin, yaw = sensor_pose(street, frame, sensor)
    scan = cast(sensor, street.layers_at(frame, near=origin[:2]), None, origin, yaw, rng)
    counts = np.bincount(scan.owner, minlength=len(street.objects))
    kinds = np.array([o.kind for o in street.objects])
    centers = street.centers_at(frame)
    yaws = np.array([o.yaw for o in street.objects]) - yaw
    sizes = np.array([o.size for o in street.objects])
    local = to_sensor(centers[:, :2], centers[:, 2], origin, yaw)
    dist = np.linalg.norm(local[:, :2], axis=1)

    labelled = ((kinds == KIND_VEHICLE) | (kinds == KIND_PEDESTRIAN)) & (dist <= labels.label_range)
    labelled &= counts >= labels.min_points
    idx = np.flatnonzero(labelled)
    idx = idx[np.argsort([street.objects[i].track_id for i in idx], kind="stable")]
    gt = Boxes(local[idx], sizes[idx], wrap_angle(yaws[idx]),
               [street.objects[i].label for i in idx], None, [str(street.objects[i].track_id) for i in idx])
    ratio = counts[idx] / np.maximum(expected_points(gt, sensor), 1e-6)
    occluded = np.where(ratio >= 0.4, 0, np.where(ratio >= 0.15, 1, 2))

    vehicles = idx[kinds[idx] == KIND_VEHICLE]
    veh_mask = np.isin(idx, vehicles)
    clutter_idx = np.flatnonzero(((kinds == KIND_CLUTTER) | (kinds == KIND_PEDESTRIAN)) & (dist < 80))
    clutter = Boxes(local[clutter_idx], sizes[clutter_idx], yaws[clutter_idx])
    confusion = np.array([street.objects[i].confusion for i in clutter_idx])
    names = np.array([street.objects[i].name for i in clutter_idx], dtype=object)
    ground_owner = np.flatnonzero((kinds == KIND_GROUND) | (kinds == KIND_STRUCTURE))
    gsel = np.isin(scan.owner, ground_owner) & (np.linalg.norm(scan.points[:, :2], axis=1) > 5.0)
    gsel &= np.linalg.norm(scan.points[:, :2], axis=1) < detector.far_range[1]
    gsel &= scan.points[:, 2] < -sensor.mount_height + 0.3
    dets, kind, source = detect(gt[veh_mask], counts[vehicles], clutter, counts[clutter_idx], confusion,
                                scan.points[gsel, :3].astype(np.float64), -sensor.mount_height, rng, detector, names)
    return FrameResult(scan, gt, counts[idx], occluded, dets, kind, source)


def _parameters(sequences, frames, seed, sensor, scene, detector, labels, shape_points, test_fraction) -> dict:
    return {
        "format": "synthcars",
        "version": FORMAT_VERSION,
        "seed": seed,
        "sequences": sequences,
        "frames": frames,
        "shape_points": shape_points,
        "test_fraction": test_fraction,
        "sensor": sensor.to_dict(),
        "scene": scene.to_dict(),
        "detector": detector.to_dict(),
        "labels": {"label_range": labels.label_range, "min_points": labels.min_points},
    }


def _jsonable(value):
    return json.loads(json.dumps(value, default=lambda v: v.tolist() if hasattr(v, "tolist") else str(v)))


def generate(
    out_dir: str | Path,
    sequences: int,
    frames: int,
    seed: int,
    *,
    sensor: Sensor | None = None,
    scene: SceneParams | None = None,
    detector: DetectorParams | None = None,
    labels: LabelParams | None = None,
    shape_points: int = 16384,
    test_fraction: float = 0.2,
    overwrite: bool = False,
    progress: bool = True,
) -> dict:
    """Write a SynthCars dataset; returns the ``meta.json`` content.

    Re-running with the same parameters skips finished sequences (a sequence is
    finished when its label file exists: it is written last, atomically). Different
    parameters over an existing dataset raise :class:`ConfigError` unless ``overwrite``.
    """
    if sequences < 1 or frames < 1:
        raise ConfigError(f"need at least one sequence and one frame (got {sequences}, {frames})")
    if shape_points < 16384:
        raise ConfigError(f"shape_points must be >= 16384 (got {shape_points})")
    if not 0.0 <= test_fraction < 1.0:
        raise ConfigError(f"test_fraction must be in [0, 1) (got {test_fraction})")
    sensor, scene = sensor or Sensor(), scene or SceneParams()
    detector, labels = detector or DetectorParams(), labels or LabelParams()
    out = Path(out_dir)
    params = _jsonable(_parameters(sequences, frames, seed, sensor, scene, detector, labels, shape_points,
                                   test_fraction))
    meta_path = out / "meta.json"
    old: dict[str, Any] = {}
    if meta_path.exists():
        try:
            old = json.loads(meta_path.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise DataError(f"{meta_path}: unreadable ({exc})") from exc
        if old.get("parameters") != params:
            if not overwrite:
                raise ConfigError(f"{out} holds a SynthCars dataset with other parameters; use --overwrite")
        if overwrite:
            for sub in ("training", "detections/synthetic", "shapes", "meta.json"):
                path = out / sub
                if path.is_dir():
                    shutil.rmtree(path)
                elif path.exists():
                    path.unlink()
    splits = splits_for(sequences, test_fraction)
    split_of = {name: split for split, names in splits.items() for name in names}
    meta = {"parameters": params, "splits": splits, "complete": False, "frame_rate_hz": 1.0 / scene.frame_dt,
            "labels_of_families": LABELS, "sequences": {}}
    out.mkdir(parents=True, exist_ok=True)
    # a finished dataset re-run with its own parameters is left untouched, meta.json's time
    # included: caches extracted from it (their fingerprint reads the files' times) stay valid
    finished = not overwrite and old.get("complete") is True and old.get("parameters") == params
    if not finished:
        writer.write_text(meta_path, [json.dumps(meta, indent=1, sort_keys=True)])
    calib = writer.calibration()
    bar = tqdm(total=sequences * frames, desc="synth", unit="frame", disable=not progress)
    for index in range(sequences):
        name = f"{index:04d}"
        split = split_of[name]
        street = build_sequence(seed, index, frames, split, scene)
        label_path = out / "training" / "label_02" / f"{name}.txt"
        if label_path.exists():
            seen = {int(line.split()[1]) for line in label_path.read_text().splitlines() if line.strip()}
            bar.update(frames)
        else:
            seen = _write_sequence(out, name, index, split, street, seed, sensor, detector, labels, calib, bar)
        tracks = {}
        for o in street.objects:
            if o.track_id in seen:
                tracks[str(o.track_id)] = {"name": o.name, "label": o.label, "size": np.round(o.size, 6).tolist(),
                                           "moving": o.moving}
        for o in street.objects:
            path = out / "shapes" / name / f"{o.track_id}.npy"
            if o.model is not None and o.track_id in seen and not path.exists():
                rng = seeded_rng(seed, SPLIT_CODES[split], index, SHAPES_STREAM, o.track_id)  # one stream per track
                writer.write_npy(path, canonical_shape(o.model, shape_points, rng))
        meta["sequences"][name] = {"split": split, "tracks": tracks, "frames": frames}
    bar.close()
    meta["complete"] = True
    if not finished or _jsonable(meta) != old:
        writer.write_text(meta_path, [json.dumps(_jsonable(meta), indent=1, sort_keys=True)])
    return meta


def _write_sequence(out, name, index, split, street, seed, sensor, detector, labels, calib, bar) -> set[int]:
    lines: list[str] = []
    seen: set[int] = set()
    for f in range(street.frames):
        rng = seeded_rng(seed, SPLIT_CODES[split], index, FRAME_STREAM, f)
        res = simulate_frame(street, f, sensor, rng, detector, labels)
        writer.write_bin(out / "training" / "velodyne" / name / f"{f:06d}.bin", res.scan.points)
        writer.write_text(out / "detections" / "synthetic" / name / f"{f:06d}.txt",
                          writer.detection_lines(res.detections, calib))
        writer.write_text(out / "detections" / "synthetic" / name / f"{f:06d}{writer.KIND_SUFFIX}",
                          writer.kind_lines(res.detection_kind, res.detection_source))
        lines.extend(writer.tracking_label_lines(res.gt, f, res.occluded, calib))
        seen.update(int(t) for t in res.gt.track_id)
        bar.update(1)
    calib.write(_ensure(out / "training" / "calib" / f"{name}.txt"))
    z = sensor.mount_height
    writer.write_text(out / "training" / "oxts" / f"{name}.txt",
                      writer.oxts_lines(street.ego_xy, street.ego_yaw, z, street.params.frame_dt))
    writer.write_text(out / "training" / "poses" / f"{name}.txt", writer.pose_lines(street.ego_xy, street.ego_yaw, z))
    writer.write_text(out / "training" / "label_02" / f"{name}.txt", lines)  # last: marks the sequence done
    return seen


def _ensure(path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    return path
