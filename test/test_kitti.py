"""KITTI readers on the real samples (tracking, object, PointRCNN results) and bad input."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from pcc_ros.data.kitti import (
    FRAME_PERIOD_NS,
    KITTI_EPOCH_NS,
    KittiObject,
    KittiTracking,
    oxts_to_poses,
    read_detections,
    read_oxts,
    read_timestamps,
    read_velodyne,
)
from pcc_ros.data.kitti_format import Calibration
from pcc_ros.errors import DataError

VEHICLES = ("Car", "Van")


def points_in_boxes_count(points: np.ndarray, center: np.ndarray, size: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """Points inside each rotated box, one vectorised (boxes x points) pass."""
    d = points[None, :, :3].astype(np.float64) - center[:, None, :]
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    lx = c * d[..., 0] + s * d[..., 1]
    ly = -s * d[..., 0] + c * d[..., 1]
    half = size[:, None, :] / 2.0
    inside = (np.abs(lx) <= half[..., 0]) & (np.abs(ly) <= half[..., 1]) & (np.abs(d[..., 2]) <= half[..., 2])
    return inside.sum(axis=1)


@pytest.fixture(scope="module")
def tracking_frames(shared_data):
    root = shared_data / "kitti_tracking"
    reader = KittiTracking(root)
    return list(reader.frames("0000", root / "detections" / "pointrcnn", stop=4))


def test_velodyne_reader(shared_data):
    points = read_velodyne(shared_data / "kitti_tracking/training/velodyne/0000/000000.bin")
    assert points.dtype == np.float32 and points.shape[1] == 4 and len(points) > 100_000
    assert np.isfinite(points).all()
    assert 0.0 <= points[:, 3].min() and points[:, 3].max() <= 1.0  # reflectance


def test_tracking_frames(tracking_frames):
    assert [f.index for f in tracking_frames] == [0, 1, 2, 3]
    assert [f.stamp_ns for f in tracking_frames] == [KITTI_EPOCH_NS + i * FRAME_PERIOD_NS for i in range(4)]
    first = tracking_frames[0]
    assert first.frame_id == "velodyne" and first.fields == ("x", "y", "z", "intensity")
    assert first.pose is None  # the sample has no oxts
    gt = first.ground_truth
    assert "DontCare" in gt.label.tolist()
    assert set(gt.track_id[gt.label == "DontCare"]) == {""}
    assert set(gt.track_id[gt.label != "DontCare"]) == {"0", "1", "2"}
    # the same track keeps its id and moves smoothly between frames
    van = [f.ground_truth[f.ground_truth.track_id == "0"] for f in tracking_frames]
    steps = np.linalg.norm(np.diff(np.stack([v.center[0] for v in van]), axis=0), axis=1)
    assert (steps < 0.5).all()
    dets = first.detections
    assert len(dets) == 3 and set(dets.label) == {"Car"}
    assert dets.score.max() > 8.0  # raw PointRCNN logits, kept as they are


def test_labelled_vehicles_contain_points(shared_data):
    """Camera -> LiDAR conversion check: labelled vehicles within 40 m hold LiDAR points."""
    root = shared_data / "kitti_tracking"
    held, total = 0, 0
    for frame in KittiTracking(root).frames("0000", stop=20):
        gt = frame.ground_truth
        near = np.isin(gt.label, VEHICLES) & (np.linalg.norm(gt.center[:, :2], axis=1) < 40.0)
        counts = points_in_boxes_count(frame.points, gt.center[near], gt.size[near], gt.yaw[near])
        held += int(np.count_nonzero(counts >= 20))
        total += int(np.count_nonzero(near))
    assert total >= 20
    assert held / total >= 0.8
    # and a wrong convention would fail: swap length and width -> far fewer points
    frame = next(KittiTracking(root).frames("0000", stop=1))
    gt = frame.ground_truth[frame.ground_truth.label == "Van"]
    right = points_in_boxes_count(frame.points, gt.center, gt.size, gt.yaw)[0]
    wrong = points_in_boxes_count(frame.points, gt.center, gt.size, gt.yaw + np.pi / 2)[0]
    assert right > 100 and wrong < right * 0.8


def test_object_frames(shared_data):
    root = shared_data / "kitti_object"
    frames = list(KittiObject(root).frames(stop=6))
    assert [f.index for f in frames] == list(range(6))
    near_counts, all_counts = [], []
    for frame in frames:
        assert frame.ground_truth is not None and frame.detections is None
        gt = frame.ground_truth[frame.ground_truth.label != "DontCare"]
        counts = points_in_boxes_count(frame.points, gt.center, gt.size, gt.yaw)
        all_counts.extend(counts.tolist())
        near_counts.extend(counts[np.linalg.norm(gt.center[:, :2], axis=1) < 40.0].tolist())
    # only 5 cars in these 6 frames, so every labelled object counts here
    assert len(near_counts) >= 5 and min(near_counts) >= 20
    assert min(all_counts) > 0


def test_detections_match_labelled_cars(shared_data):
    """The best PointRCNN detection lies on a labelled vehicle (same conversion for both)."""
    root = shared_data / "kitti_tracking"
    calib = Calibration.read(root / "training/calib/0000.txt")
    dets = read_detections(root / "detections/pointrcnn/0000/000000.txt", calib)
    frame = next(KittiTracking(root).frames("0000", stop=1))
    gt = frame.ground_truth[np.isin(frame.ground_truth.label, VEHICLES)]
    best = dets[int(np.argmax(dets.score))]
    dist = np.linalg.norm(gt.center - best.center, axis=1).min()
    assert dist < 0.5


def test_truncated_scan_names_file(tmp_path):
    path = tmp_path / "000000.bin"
    path.write_bytes(np.zeros(10, dtype=np.float32).tobytes()[:-2])
    with pytest.raises(DataError, match=r"000000\.bin.*multiple of 16"):
        read_velodyne(path)
    with pytest.raises(DataError, match="cannot read"):
        read_velodyne(tmp_path / "missing.bin")


def _copy_tracking(shared_data: Path, dst: Path, frames: int = 2) -> Path:
    src = shared_data / "kitti_tracking/training"
    (dst / "training/velodyne/0000").mkdir(parents=True)
    for i in range(frames):
        shutil.copy(src / f"velodyne/0000/{i:06d}.bin", dst / f"training/velodyne/0000/{i:06d}.bin")
    shutil.copytree(src / "calib", dst / "training/calib")
    shutil.copytree(src / "label_02", dst / "training/label_02")
    return dst


def test_malformed_label_line_names_file_and_line(shared_data, tmp_path):
    root = _copy_tracking(shared_data, tmp_path)
    label = root / "training/label_02/0000.txt"
    lines = label.read_text().splitlines()
    lines[3] = lines[3].rsplit(" ", 2)[0]  # drop two columns
    label.write_text("\n".join(lines) + "\n")
    with pytest.raises(DataError, match=r"0000.txt:4: expected 17 or 18 columns"):
        list(KittiTracking(root).frames("0000"))


def test_calibration_without_keys(shared_data, tmp_path):
    root = _copy_tracking(shared_data, tmp_path)
    calib = root / "training/calib/0000.txt"
    calib.write_text("".join(line + "\n" for line in calib.read_text().splitlines() if "velo_to_cam" not in line))
    with pytest.raises(DataError, match="lacks Tr_velo_to_cam"):
        list(KittiTracking(root).frames("0000"))


def test_unknown_classes_kept_and_counted(shared_data, tmp_path, caplog):
    root = _copy_tracking(shared_data, tmp_path)
    label = root / "training/label_02/0000.txt"
    label.write_text(label.read_text().replace(" Cyclist ", " Hovercraft "))
    reader = KittiTracking(root)
    frames = list(reader.frames("0000"))
    assert "Hovercraft" in frames[0].ground_truth.label.tolist()
    assert reader.unknown_classes["Hovercraft"] == 20  # every labelled frame of the file
    assert "Hovercraft" in caplog.text


def test_missing_detection_files_are_counted(shared_data, tmp_path, caplog):
    root = _copy_tracking(shared_data, tmp_path, frames=3)
    dets = tmp_path / "dets/0000"
    dets.mkdir(parents=True)
    shutil.copy(shared_data / "kitti_tracking/detections/pointrcnn/0000/000000.txt", dets / "000000.txt")
    reader = KittiTracking(root)
    frames = list(reader.frames("0000", tmp_path / "dets"))
    assert [len(f.detections) for f in frames] == [3, 0, 0]
    assert reader.missing_detections == 2 and "2 frames had no detector-result file" in caplog.text


def test_unknown_sequence(shared_data):
    with pytest.raises(DataError, match="no such sequence"):
        list(KittiTracking(shared_data / "kitti_tracking").frames("0042"))
    with pytest.raises(DataError, match="not a KITTI directory"):
        KittiTracking(shared_data / "nuscenes_sample")


def _oxts_records(step_m: float = 0.35) -> list[str]:
    """Two KITTI-raw-format OXTS records (30 values): the second moved ``step_m`` along the heading.

    The displacement is put into latitude / longitude with the inverse of the devkit's
    Mercator projection, so a correct oxts -> pose conversion returns it in the first IMU frame.
    """
    lat0, lon0, alt, roll, pitch, yaw = 49.011212804408, 8.4228850417969, 112.83, 0.022, 1e-05, -1.2219
    scale = np.cos(np.deg2rad(lat0))
    radius = 6378137.0
    east, north = step_m * np.cos(yaw), step_m * np.sin(yaw)
    lon1 = lon0 + np.rad2deg(east / (scale * radius))
    my0 = scale * radius * np.log(np.tan(np.deg2rad(90.0 + lat0) / 2.0))
    lat1 = 2.0 * np.rad2deg(np.arctan(np.exp((my0 + north) / (scale * radius)))) - 90.0
    tail = " ".join(["0.0"] * 19) + " 4 10 4 4 0"
    return [f"{float(la)!r} {float(lo)!r} {alt} {roll} {pitch} {yaw} {tail}" for la, lo in ((lat0, lon0), (lat1, lon1))]


OXTS = _oxts_records()


def test_oxts_poses(tmp_path):
    path = tmp_path / "0000.txt"
    path.write_text("\n".join(OXTS) + "\n")
    oxts = read_oxts(path)
    assert oxts.shape == (2, 30)
    poses = oxts_to_poses(oxts)
    assert np.allclose(poses[0], np.eye(4))
    assert np.allclose(poses[1, :3, :3] @ poses[1, :3, :3].T, np.eye(3))
    # 0.35 m straight ahead of the first IMU frame (small pitch / roll tilt it by < 1 cm)
    assert np.allclose(poses[1, :3, 3], [0.35, 0.0, 0.0], atol=0.01)
    path.write_text(OXTS[0] + "\n8.1 oops\n")
    with pytest.raises(DataError, match=r"0000.txt:2"):
        read_oxts(path)


def test_tracking_poses_and_timestamps(shared_data, tmp_path):
    root = _copy_tracking(shared_data, tmp_path)
    (root / "training/oxts").mkdir()
    (root / "training/oxts/0000.txt").write_text("\n".join(OXTS) + "\n")
    (root / "training/oxts/0000").mkdir()
    (root / "training/oxts/0000/timestamps.txt").write_text(
        "2011-09-26 13:02:25.964389445\n2011-09-26 13:02:26.074415872\n"
    )
    frames = list(KittiTracking(root).frames("0000"))
    stamps = [f.stamp_ns for f in frames]
    assert stamps == read_timestamps(root / "training/oxts/0000/timestamps.txt").tolist()
    assert stamps[0] % 1_000_000_000 == 964389445
    calib = Calibration.read(root / "training/calib/0000.txt")
    imu_to_velo = np.eye(4)
    imu_to_velo[:3] = calib.Tr_imu_to_velo
    # odom <- velodyne composed of odom <- imu and the static base_link (imu) <- velodyne
    assert np.allclose(frames[0].pose, np.linalg.inv(imu_to_velo))
    assert np.allclose(frames[1].extras["sensor_to_base"], np.linalg.inv(imu_to_velo))
    assert np.allclose(frames[1].pose @ imu_to_velo, oxts_to_poses(read_oxts(root / "training/oxts/0000.txt"))[1])
