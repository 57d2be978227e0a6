"""nuScenes table reader on a tiny v1.0 table set built around the real LIDAR_TOP sweep.

``annotations_lidar_frame.json`` holds the sample's boxes in the LiDAR frame and the
lidar -> ego and ego -> global poses. The fixture moves every box to the global frame and
writes the official tables (``scene``, ``sample``, ``sample_data``, ``sample_annotation``,
``instance``, ``category``, ``ego_pose``, ``calibrated_sensor``, ``sensor``) the way the
nuScenes schema stores them (size w, l, h; quaternions w, x, y, z); the reader must then
recover the LiDAR-frame boxes. A second sample reuses the sweep with another ego pose, so
the test also covers the scene's sample chain and a pose that is not the first one.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pcc_ros.data.nuscenes import NuScenes, category_to_label
from pcc_ros.errors import DataError
from pcc_ros.geometry.rotations import quaternion_to_matrix, xyzw_from_wxyz

# mmdetection3d's short names -> a full nuScenes category; "ignore" -> a made-up category
# to exercise the pass-through of unknown names.
CATEGORIES = {
    "car": "vehicle.car",
    "pedestrian": "human.pedestrian.adult",
    "barrier": "movable_object.barrier",
    "traffic_cone": "movable_object.trafficcone",
    "truck": "vehicle.truck",
    "bicycle": "vehicle.bicycle",
    "bus": "vehicle.bus.rigid",
    "construction_vehicle": "vehicle.construction",
    "ignore": "mystery.object",
}


def _record(matrix: np.ndarray) -> dict:
    x, y, z, w = Rotation.from_matrix(matrix[:3, :3]).as_quat()
    return {"translation": matrix[:3, 3].tolist(), "rotation": [w, x, y, z]}


def _rz(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def build_tables(shared_data: Path, root: Path, version: str = "v1.0-mini") -> dict:
    sample = json.loads((shared_data / "nuscenes_sample/annotations_lidar_frame.json").read_text())
    lidar_dir = root / "samples/LIDAR_TOP"
    lidar_dir.mkdir(parents=True)
    (lidar_dir / sample["lidar_file"]).symlink_to(shared_data / "nuscenes_sample" / sample["lidar_file"])
    lidar2ego = np.array(sample["lidar2ego"])
    ego2global = [np.array(sample["ego2global"]), np.array(sample["ego2global"])]
    ego2global[1][:3, :3] = _rz(0.4) @ ego2global[1][:3, :3]  # second sample: turned and moved
    ego2global[1][:3, 3] += [3.0, -2.0, 0.1]
    anns = sample["annotations"]
    stamp_us = round(sample["timestamp"] * 1e6)
    tables: dict[str, list[dict]] = {name: [] for name in (
        "scene", "sample", "sample_data", "sample_annotation", "instance", "category", "ego_pose",
        "calibrated_sensor", "sensor")}
    tables["sensor"] = [{"token": "sensor_lidar", "channel": "LIDAR_TOP", "modality": "lidar"},
                        {"token": "sensor_cam", "channel": "CAM_FRONT", "modality": "camera"}]
    tables["calibrated_sensor"] = [
        {"token": "cs_lidar", "sensor_token": "sensor_lidar", "camera_intrinsic": [], **_record(lidar2ego)},
        {"token": "cs_cam", "sensor_token": "sensor_cam", "camera_intrinsic": np.eye(3).tolist(),
         **_record(np.eye(4))},
    ]
    tables["category"] = [{"token": f"cat_{short}", "name": full, "description": ""}
                          for short, full in CATEGORIES.items()]
    tables["instance"] = [{"token": f"inst_{i}", "category_token": f"cat_{a['category']}", "nbr_annotations": 2,
                           "first_annotation_token": f"ann_0_{i}", "last_annotation_token": f"ann_1_{i}"}
                          for i, a in enumerate(anns)]
    tables["scene"] = [{"token": "scene_tok", "log_token": "log", "nbr_samples": 2, "name": "scene-0061",
                        "description": "", "first_sample_token": "sample_0", "last_sample_token": "sample_1"}]
    for k in range(2):
        stamp = stamp_us + k * 500_000
        tables["sample"].append({"token": f"sample_{k}", "timestamp": stamp, "scene_token": "scene_tok",
                                 "prev": f"sample_{k - 1}" if k else "", "next": "sample_1" if k == 0 else ""})
        tables["ego_pose"].append({"token": f"ego_{k}", "timestamp": stamp, **_record(ego2global[k])})
        tables["sample_data"].append({
            "token": f"sd_{k}", "sample_token": f"sample_{k}", "ego_pose_token": f"ego_{k}",
            "calibrated_sensor_token": "cs_lidar", "timestamp": stamp, "fileformat": "pcd", "is_key_frame": True,
            "height": 0, "width": 0, "filename": f"samples/LIDAR_TOP/{sample['lidar_file']}", "prev": "", "next": ""})
        # a camera image and a non-key LiDAR sweep of the same sample must be ignored
        tables["sample_data"].append({
            "token": f"cam_{k}", "sample_token": f"sample_{k}", "ego_pose_token": f"ego_{k}",
            "calibrated_sensor_token": "cs_cam", "timestamp": stamp, "fileformat": "jpg", "is_key_frame": True,
            "height": 900, "width": 1600, "filename": "samples/CAM_FRONT/none.jpg", "prev": "", "next": ""})
        tables["sample_data"].append({
            "token": f"sweep_{k}", "sample_token": f"sample_{k}", "ego_pose_token": f"ego_{k}",
            "calibrated_sensor_token": "cs_lidar", "timestamp": stamp + 50_000, "fileformat": "pcd",
            "is_key_frame": False, "height": 0, "width": 0, "filename": "sweeps/LIDAR_TOP/none.pcd.bin",
            "prev": "", "next": ""})
        to_global = ego2global[k] @ lidar2ego
        for i, a in enumerate(anns):
            x, y, z, length, width, height, yaw = a["box_lidar_xyz_center_lwh_yaw"]
            box = np.eye(4)
            box[:3, :3] = _rz(yaw)
            box[:3, 3] = [x, y, z]
            tables["sample_annotation"].append({
                "token": f"ann_{k}_{i}", "sample_token": f"sample_{k}", "instance_token": f"inst_{i}",
                "visibility_token": "4", "attribute_tokens": [], "size": [width, length, height],
                "num_lidar_pts": a["num_lidar_pts"], "num_radar_pts": 0,
                "prev": f"ann_0_{i}" if k else "", "next": "" if k else f"ann_1_{i}",
                **_record(to_global @ box)})
    (root / version).mkdir()
    for name, rows in tables.items():
        (root / version / f"{name}.json").write_text(json.dumps(rows))
    return sample


@pytest.fixture()
def nuscenes_root(shared_data, tmp_path):
    sample = build_tables(shared_data, tmp_path)
    return tmp_path, sample


def test_quaternion_matches_scipy():
    rng = np.random.default_rng(0)
    q = rng.normal(size=(5, 4))
    ours = quaternion_to_matrix(xyzw_from_wxyz(q))
    theirs = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()
    assert np.allclose(ours, theirs)


def test_category_labels():
    assert category_to_label("vehicle.car") == "Car"
    assert category_to_label("vehicle.bus.bendy") == "Bus"
    assert category_to_label("human.pedestrian.child") == "Pedestrian"
    assert category_to_label("vehicle.emergency.ambulance") == "Van"
    assert category_to_label("mystery.object") == "mystery.object"


def test_reader_recovers_lidar_boxes(nuscenes_root):
    root, sample = nuscenes_root
    frames = list(NuScenes(root, "v1.0-mini").frames())
    assert [f.index for f in frames] == [0, 1]
    assert all(f.sequence == "scene-0061" and f.frame_id == "LIDAR_TOP" for f in frames)
    assert frames[0].stamp_ns == round(sample["timestamp"] * 1e6) * 1000
    assert frames[1].stamp_ns - frames[0].stamp_ns == 500_000_000
    expected = np.array([a["box_lidar_xyz_center_lwh_yaw"] for a in sample["annotations"]])
    for frame in frames:
        gt = frame.ground_truth
        assert frame.fields == ("x", "y", "z", "intensity", "ring") and frame.points.shape == (34688, 5)
        assert np.allclose(gt.center, expected[:, :3], atol=1e-6)
        assert np.allclose(gt.size, expected[:, 3:6], atol=1e-9)
        assert np.allclose(np.angle(np.exp(1j * (gt.yaw - expected[:, 6]))), 0.0, atol=1e-6)
        assert gt.track_id.tolist() == [f"inst_{i}" for i in range(len(expected))]
        assert np.allclose(frame.extras["sensor_to_base"], np.array(sample["lidar2ego"]), atol=1e-6)
    assert np.allclose(frames[0].pose, np.array(sample["ego2global"]) @ np.array(sample["lidar2ego"]), atol=1e-6)
    gt, extras = frames[0].ground_truth, frames[0].extras
    assert gt.label[extras["category"] == "vehicle.car"].tolist() == ["Car"] * 8
    assert "mystery.object" in gt.label.tolist()
    assert extras["num_lidar_pts"].tolist() == [a["num_lidar_pts"] for a in sample["annotations"]]


def test_annotated_point_counts_reproduced(nuscenes_root):
    """Boxes recovered from global tables hold the annotators' num_lidar_pts."""
    root, _ = nuscenes_root
    frame = next(NuScenes(root).frames("scene-0061"))
    gt = frame.ground_truth
    d = frame.points[None, :, :3].astype(np.float64) - gt.center[:, None, :]
    c, s = np.cos(gt.yaw)[:, None], np.sin(gt.yaw)[:, None]
    lx, ly = c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]
    half = gt.size[:, None, :] / 2
    counts = ((np.abs(lx) <= half[..., 0]) & (np.abs(ly) <= half[..., 1]) & (np.abs(d[..., 2]) <= half[..., 2])).sum(1)
    expected = frame.extras["num_lidar_pts"]
    # box-edge rounding may move a point in or out of a box; most boxes agree exactly
    assert np.mean(np.abs(counts - expected) <= 1) >= 0.9
    cars = frame.extras["category"] == "vehicle.car"
    assert np.abs(counts[cars] - expected[cars]).max() <= 2


def test_bad_inputs(nuscenes_root):
    root, sample = nuscenes_root
    with pytest.raises(DataError, match="wrong --version"):
        NuScenes(root, "v1.0-trainval")
    with pytest.raises(DataError, match="no scene 'scene-9999'"):
        list(NuScenes(root).frames("scene-9999"))
    # a truncated sweep names its file
    path = root / "samples/LIDAR_TOP" / sample["lidar_file"]
    raw = path.read_bytes()
    path.unlink()
    path.write_bytes(raw[:-3])
    with pytest.raises(DataError, match=r"pcd\.bin.*multiple of 20"):
        list(NuScenes(root).frames())
    (root / "v1.0-mini/ego_pose.json").write_text("[{")
    with pytest.raises(DataError, match=r"ego_pose.json:1: invalid JSON"):
        NuScenes(root)
    (root / "v1.0-mini/ego_pose.json").unlink()
    with pytest.raises(DataError, match=r"ego_pose\.json: cannot read"):
        NuScenes(root)


def test_non_finite_annotation_skipped_and_counted(nuscenes_root, caplog):
    root, _ = nuscenes_root
    path = root / "v1.0-mini/sample_annotation.json"
    anns = json.loads(path.read_text())
    anns[0]["size"] = [float("nan"), 1.0, 1.0]
    path.write_text(json.dumps(anns))
    reader = NuScenes(root)
    frames = list(reader.frames())
    assert len(frames[0].ground_truth) == len(frames[1].ground_truth) - 1
    assert sum(reader.skipped.values()) == 1 and "non-finite" in caplog.text
