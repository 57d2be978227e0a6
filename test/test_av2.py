"""Argoverse 2: `pcc convert av2` round trip on a log the tests write (test/av2_fixture.py), the tool
chain on it (extract, eval --real, replay), and logs with missing or damaged tables."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from av2_fixture import read_table, write_log
from conftest import assert_named_failure, run_cli
from scipy.spatial.transform import Rotation

from pcc_ros.cli.main import main
from pcc_ros.data.av2 import CATEGORY_TO_LABEL, CLASS_MAP, Av2Log, category_to_label
from pcc_ros.data.bag import decode, iter_messages, open_bag, read_frames
from pcc_ros.data.instances import InstanceCache
from pcc_ros.data.sources import count_frames, kind_of, open_frames
from pcc_ros.errors import DataError
from pcc_ros.pipeline.config import parse_class_map


@pytest.fixture(scope="module")
def av2_log(tmp_path_factory):
    return write_log(tmp_path_factory.mktemp("av2") / "0c6e62d7-bdfa-3061-8d3d-03b13aa21f68")


def _se3(rows: dict[str, np.ndarray]) -> np.ndarray:
    """The tests' own reading of AV2 qw..tz_m columns (scipy, x y z w order)."""
    q = np.column_stack([rows["qx"], rows["qy"], rows["qz"], rows["qw"]]).astype(np.float64)
    out = np.tile(np.eye(4), (len(q), 1, 1))
    out[:, :3, :3] = Rotation.from_quat(q).as_matrix()
    out[:, :3, 3] = np.column_stack([rows["tx_m"], rows["ty_m"], rows["tz_m"]])
    return out


def _tf_static(bag) -> dict[tuple[str, str], np.ndarray]:
    edges = {}
    with open_bag(bag) as reader:
        for connection, time_ns, raw in iter_messages(reader, bag, [c for c in reader.connections
                                                                    if c.topic == "/tf_static"]):
            for t in decode(reader, raw, connection, time_ns, bag).transforms:
                m = np.eye(4)
                q, p = t.transform.rotation, t.transform.translation
                m[:3, :3] = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
                m[:3, 3] = [p.x, p.y, p.z]
                edges[(t.header.frame_id, t.child_frame_id)] = m
    return edges


def _check_bag(bag, log, frame: str, first: int = 0) -> None:
    """Points, boxes, ids and tf of the bag equal the feather tables after the documented transforms."""
    ann = read_table(log.root / "annotations.feather")
    poses = read_table(log.root / "city_SE3_egovehicle.feather")
    calib = read_table(log.root / "calibration" / "egovehicle_SE3_sensor.feather")
    ego_from_sensor = dict(zip(calib["sensor_name"].tolist(), _se3(calib)))
    mount = np.eye(4) if frame == "ego_vehicle" else ego_from_sensor[frame]
    frames = list(read_frames(bag))
    assert [f.stamp_ns for f in frames] == log.stamps[first:first + len(frames)]
    ann_boxes = _se3(ann)
    for f in frames:
        sweep = read_table(log.root / "sensors" / "lidar" / f"{f.stamp_ns}.feather")
        xyz = np.column_stack([sweep["x"], sweep["y"], sweep["z"]]).astype(np.float64)
        xyz = (xyz - mount[:3, 3]) @ mount[:3, :3]  # inv(ego <- frame) applied to the ego-frame sweep
        assert f.frame_id == frame and f.fields == ("x", "y", "z", "intensity", "ring", "time")
        np.testing.assert_allclose(f.points[:, :3], xyz, atol=2e-5)
        np.testing.assert_array_equal(f.points[:, 3], sweep["intensity"])
        np.testing.assert_array_equal(f.points[:, 4], sweep["laser_number"])
        np.testing.assert_allclose(f.points[:, 5], sweep["offset_ns"] * 1e-9, rtol=1e-6)
        rows = np.flatnonzero(ann["timestamp_ns"] == f.stamp_ns)
        gt = f.ground_truth
        assert gt.track_id.tolist() == ann["track_uuid"][rows].tolist()
        assert gt.label.tolist() == [CATEGORY_TO_LABEL[c] for c in ann["category"][rows]]
        in_frame = np.linalg.inv(mount) @ ann_boxes[rows]
        np.testing.assert_allclose(gt.center, in_frame[:, :3, 3], atol=1e-6)
        np.testing.assert_allclose(gt.size, np.column_stack([ann["length_m"], ann["width_m"], ann["height_m"]])[rows])
        yaw = np.arctan2(in_frame[:, 1, 0], in_frame[:, 0, 0])
        np.testing.assert_allclose(np.angle(np.exp(1j * (gt.yaw - yaw))), 0.0, atol=1e-6)
        city_from_ego = _se3(poses)[np.flatnonzero(poses["timestamp_ns"] == f.stamp_ns)[0]]
        np.testing.assert_allclose(f.pose, city_from_ego @ mount, atol=1e-9)
        assert f.extras["world_frame"] == "city"
    static = _tf_static(bag)
    assert set(static) == {("ego_vehicle", name) for name in ego_from_sensor}
    for name, m in ego_from_sensor.items():
        np.testing.assert_allclose(static[("ego_vehicle", name)], m, atol=1e-9)


def test_every_category_maps_and_the_class_map_string_is_the_table():
    assert len(CATEGORY_TO_LABEL) == 30
    assert parse_class_map(CLASS_MAP) == CATEGORY_TO_LABEL
    assert category_to_label("REGULAR_VEHICLE") == "Car" and category_to_label("BOLLARD") == "Misc"
    assert category_to_label("NEW_CATEGORY") == "NEW_CATEGORY"


def test_convert_in_the_recorded_ego_frame_round_trips(av2_log, tmp_path):
    bag = tmp_path / "ego"
    assert main(["convert", "av2", str(av2_log.root), "--frame", "ego_vehicle", "--out", str(bag)]) == 0
    _check_bag(bag, av2_log, "ego_vehicle")
    kept = sum(len(f.ground_truth) for f in read_frames(bag))
    assert kept == av2_log.annotation_count - av2_log.off_sweep_annotations  # every annotation on a sweep


def test_convert_in_the_up_lidar_frame_through_the_calibration(av2_log, tmp_path, caplog):
    bag = tmp_path / "up"
    caplog.set_level("INFO")
    assert main(["convert", "av2", str(av2_log.root), "--storage", "sqlite3",  # up_lidar: the default frame
                 "--first", "1", "--frames", "2", "--out", str(bag)]) == 0
    _check_bag(bag, av2_log, "up_lidar", first=1)
    # every annotation accounted for: 8 converted, 8 on the other sweeps, 1 at a stamp without a sweep
    assert "8 annotations on converted sweeps" in caplog.text
    assert "8 annotations on sweeps not converted" in caplog.text
    assert "1 annotations at a stamp without a sweep" in caplog.text


def test_unknown_or_tilted_frame_is_refused_naming_the_sensors(av2_log, tmp_path, caplog):
    rc, text = run_cli(["convert", "av2", av2_log.root, "--frame", "lidar_top", "--out", tmp_path / "x"], caplog)
    assert_named_failure(rc, text, "no sensor 'lidar_top'", "up_lidar")
    # the fixture's down_lidar is mounted upside down and a camera looks along its z: no yaw-only boxes there
    for sensor, degrees in (("down_lidar", "180"), ("ring_front_center", "90")):
        rc, text = run_cli(["convert", "av2", av2_log.root, "--frame", sensor, "--out", tmp_path / "x"], caplog)
        assert_named_failure(rc, text, f"sensor '{sensor}' is tilted {degrees} deg")
    assert not (tmp_path / "x").exists()


def test_several_logs_and_split_dirs(tmp_path):
    split = tmp_path / "val"
    first = write_log(split / "log_a", sweeps=2)
    write_log(split / "log_b", sweeps=3, seed=1, start=first.stamps[0] + 10**12)
    assert kind_of(split) == "av2" and kind_of(split / "log_a") == "av2"
    assert count_frames(split) == 5 and count_frames(split, "log_b") == 3
    assert [f.sequence for f in open_frames(split, sequence="log_a")] == ["log_a"] * 2
    assert main(["convert", "av2", str(split), "--out", str(tmp_path / "bags")]) == 0
    assert sorted(p.name for p in (tmp_path / "bags").iterdir()) == ["log_a", "log_b"]
    assert len(list(read_frames(tmp_path / "bags" / "log_b"))) == 3


def test_extract_eval_real_and_replay_run_on_av2(av2_log, tmp_path, capsys):
    bag = tmp_path / "bag"
    assert main(["convert", "av2", str(av2_log.root), "--out", str(bag)]) == 0
    for source, cache in ((av2_log.root, tmp_path / "cache_log"), (bag, tmp_path / "cache_bag")):
        assert main(["extract", str(source), "--out", str(cache), "--no-progress"]) == 0
        meta = InstanceCache.load(cache).meta
        assert len(meta["track"]) == 8  # two cars on four sweeps (Car, Van by default)
        assert set(meta["track"]) == {u for u in read_table(av2_log.root / "annotations.feather")["track_uuid"]
                                      if "car" in u}
    out = tmp_path / "real.json"
    assert main(["eval", "--real", "--real-sources", str(av2_log.root), "--backends", "input,mirror",
                 "--json", str(out)]) == 0
    result = json.loads(out.read_text())
    assert result["instances"] == 8 and result["sources"][str(av2_log.root)]["tracks"] == 2
    assert main(["replay", str(bag), "--out", str(tmp_path / "replayed"), "--backend", "mirror",
                 "--detections-topic", "/ground_truth"]) == 0
    assert "replay timing per frame (4 frames" in capsys.readouterr().out


@pytest.mark.parametrize("damage, named", [
    ("no_annotations", "annotations.feather: missing annotations"),
    ("corrupt_sweep", ".feather: unreadable LiDAR sweep"),
    ("pose_column", "city_SE3_egovehicle.feather: ego poses lacks column(s) ['qw']"),
    ("pose_missing", "city_SE3_egovehicle.feather: no pose at sweep time"),
    ("bad_sweep_name", "a sweep file must be named <timestamp_ns>.feather"),
    ("text_coordinates", "annotations column 'tx_m' has type string, expected numbers"),
    ("null_uuid", "annotations column 'track_uuid' has 1 null value(s)"),
])
def test_damaged_logs_name_the_file(av2_log, tmp_path, caplog, damage, named):
    import pyarrow as pa
    import pyarrow.feather as feather

    root = tmp_path / "log"
    shutil.copytree(av2_log.root, root)
    sweep = root / "sensors" / "lidar" / f"{av2_log.stamps[1]}.feather"
    poses = root / "city_SE3_egovehicle.feather"
    if damage == "no_annotations":
        (root / "annotations.feather").unlink()
    elif damage == "corrupt_sweep":
        sweep.write_bytes(sweep.read_bytes()[:200])
    elif damage == "pose_column":
        feather.write_feather(feather.read_table(poses).drop_columns(["qw"]), poses)
    elif damage == "pose_missing":
        table = feather.read_table(poses)
        keep = table.column("timestamp_ns").to_numpy() != av2_log.stamps[2]
        feather.write_feather(table.filter(pa.array(keep)), poses)
    elif damage in ("text_coordinates", "null_uuid"):
        path = root / "annotations.feather"
        table = feather.read_table(path)
        name = "tx_m" if damage == "text_coordinates" else "track_uuid"
        values = table.column(name).to_pylist()
        if damage == "text_coordinates":
            column = pa.array([str(v) for v in values])
        else:
            column = pa.array([None, *values[1:]], pa.string())
        feather.write_feather(table.set_column(table.column_names.index(name), name, column), path)
    else:
        sweep.rename(sweep.with_name("sweep.feather"))
    rc, text = run_cli(["convert", "av2", root, "--out", tmp_path / "bag"], caplog)
    assert_named_failure(rc, text, named, output=tmp_path / "bag")
    with pytest.raises(DataError, match="feather"):
        list(Av2Log(root).frames())


def test_float16_sweeps_are_read_exactly(av2_log):
    """AV2 stores x, y, z as float16: the reader widens them without loss (float16 -> float32 is exact)."""
    import pyarrow as pa
    import pyarrow.feather as feather

    path = av2_log.root / "sensors" / "lidar" / f"{av2_log.stamps[0]}.feather"
    assert feather.read_table(path).schema.field("x").type == pa.float16()
    points = Av2Log(av2_log.root).read_sweep(path)
    np.testing.assert_array_equal(points[:, 0], read_table(path)["x"])  # float16 values, exactly


def test_a_test_split_log_without_annotations_converts_with_no_labels(av2_log, tmp_path):
    root = tmp_path / "log"
    shutil.copytree(av2_log.root, root)
    (root / "annotations.feather").unlink()
    bag = tmp_path / "bag"
    assert main(["convert", "av2", str(root), "--no-labels", "--out", str(bag)]) == 0
    frames = list(read_frames(bag))
    assert len(frames) == 4 and all(f.ground_truth is None for f in frames)
