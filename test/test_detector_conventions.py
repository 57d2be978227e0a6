"""What real detector stacks send: numeric class ids, restamped detections, ROS 1 frame ids.

The node core on the in-process graph (the same :class:`NodeCore` the rclpy nodes host), and
one in-process rclpy node under real rclpy with real KITTI PointRCNN boxes.
"""

from __future__ import annotations

import logging

import numpy as np
import pytest
from conftest import live_pipeline_node, require_rclpy

from pcc_ros.errors import ConfigError
from pcc_ros.msg.detections import detection_array_from_boxes
from pcc_ros.msg.pointcloud2 import create_cloud, read_xyz
from pcc_ros.pipeline.config import PipelineConfig, parse_class_map
from pcc_ros.pipeline.core import Pipeline
from pcc_ros.pipeline.filter import UNJUDGED_CLASS_ID
from pcc_ros.pipeline.outputs import build_outputs
from pcc_ros.runtime.base import RELIABLE, SENSOR_DATA
from pcc_ros.runtime.local import LocalGraph, LocalRuntime
from pcc_ros.runtime.node import NodeCore
from pcc_ros.types import Boxes

CLOUD = "sensor_msgs/msg/PointCloud2"
DETS = "vision_msgs/msg/Detection3DArray"


def _scene(labels=("1", "1")):
    rng = np.random.default_rng(0)
    car1 = rng.uniform([-2, -0.85, -0.7], [2, 0.85, 0.7], size=(400, 3)) + np.array([10, 0, -0.8])
    car2 = rng.uniform([-2, -0.8, -0.7], [2, 0.8, 0.7], size=(300, 3)) + np.array([6, 5, -0.8])
    points = np.concatenate([car1, car2]).astype(np.float32)
    boxes = Boxes([[10, 0, -0.8], [6, 5, -0.8]], [[4.2, 1.8, 1.5], [4.2, 1.7, 1.5]], [0.0, 0.1],
                  list(labels), [0.9, 0.8], ["a", "b"])
    return points, boxes


def _messages(stamp_ns, labels=("1", "1"), det_stamp_ns=None, det_frame="velodyne"):
    points, boxes = _scene(labels)
    cloud = create_cloud(points, ["x", "y", "z"], "velodyne", stamp_ns)
    dets = detection_array_from_boxes(boxes, det_frame, stamp_ns if det_stamp_ns is None else det_stamp_ns)
    return cloud, dets


def _graph_node(mode="completion", **params):
    graph = LocalGraph(simulated=True)
    core = NodeCore(LocalRuntime(graph, f"{mode}_node"), f"{mode}_node", mode, {"backend": "mirror", **params},
                    threaded=False)
    driver = LocalRuntime(graph, "driver")
    pubs = (driver.create_publisher("/points", CLOUD, SENSOR_DATA),
            driver.create_publisher("/detections", DETS, RELIABLE))
    return graph, core, pubs


def test_class_map_parses_and_refuses_bad_entries():
    assert parse_class_map("") == {}
    assert parse_class_map(" 1:Car, 2:Pedestrian ,3:Cyclist") == {"1": "Car", "2": "Pedestrian", "3": "Cyclist"}
    for bad in ("1", "1:", ":Car", "1:Car, 1:Van", "1:Car, 1.0:Van", "1:a:b"):
        with pytest.raises(ConfigError, match="class_map: bad entry"):
            PipelineConfig(backend="mirror", class_map=bad)


def test_numeric_class_ids_are_completed_only_through_class_map():
    cloud, dets = _messages(1_000_000_000)
    plain, _ = Pipeline(PipelineConfig(backend="mirror")).process_messages(cloud, dets)
    assert plain.skipped == {"other class": 2} and not len(plain.completed_points)

    mapped = Pipeline(PipelineConfig(backend="mirror", class_map="1:Car, 2:Pedestrian"))
    result, originals = mapped.process_messages(cloud, dets)
    assert "other class" not in result.skipped and len(result.completed_points) > 0
    assert list(result.detections.label) == ["Car", "Car"]  # markers name the class
    assert [d.results[0].hypothesis.class_id for d in originals] == ["1", "1"]  # republished as the detector sent
    # str() of a numpy float label ('1.0') is the same id; names are matched as classes match them
    cfg = PipelineConfig(backend="mirror", class_map="1:Car, 0:car, 2.0:Van")
    assert cfg.map_labels(np.array(["1.0", " 1", "0", "2", "7", "Car", "nan"], dtype=object)).tolist() == [
        "Car", "Car", "car", "Van", "7", "Car", "nan"]
    # class_thresholds match the mapped names
    cfg = PipelineConfig(backend="mirror", class_map="1:Car", class_thresholds="Car:0.7")
    assert cfg.detection_thresholds(cfg.map_labels(np.array(["1", "2"], dtype=object))).tolist() == [0.7, 0.5]


def test_numeric_class_ids_are_reported_once_then_counted(caplog):
    graph, core, (pub_cloud, pub_dets) = _graph_node()
    completed = []
    LocalRuntime(graph, "probe").create_subscription("/completed", CLOUD, completed.append, RELIABLE)
    with caplog.at_level(logging.INFO):
        for k in (1, 2):
            cloud, dets = _messages(k * 1_000_000_000)
            pub_cloud.publish(cloud)
            pub_dets.publish(dets)
    warnings = [r.getMessage() for r in caplog.records if "class id(s)" in r.getMessage()]
    assert len(warnings) == 1 and "['1']" in warnings[0] and "class_map" in warnings[0]
    assert core.diagnostics_values()["skipped_other_class"] == "4"
    assert len(completed) == 2 and read_xyz(completed[-1]).shape[0] == 0  # nothing completed, never silently

    assert core.set_parameters({"class_map": "1:Car"}).successful
    cloud, dets = _messages(3_000_000_000)
    pub_cloud.publish(cloud)
    pub_dets.publish(dets)
    instances = read_xyz(completed[-1], ("instance",))[:, 3]
    assert set(instances.tolist()) == {0.0, 1.0}


def test_class_ids_reported_stay_bounded_within_one_frame(caplog):
    """A hostile detector with hundreds of distinct labels in one frame: at most
    ``REPORTED_CLASSES`` ids are remembered and named, however many the first frame brings."""
    from pcc_ros.runtime.diagnostics import REPORTED_CLASSES, report_other_classes

    log = logging.getLogger("pcc_ros.test.classes")
    labels = np.array([f"thing{i}" for i in range(500)], dtype=object)
    seen: set[str] = set()
    with caplog.at_level(logging.INFO):
        report_other_classes(log, "completion", labels, ("Car",), seen)
        report_other_classes(log, "completion", labels[::-1].copy(), ("Car",), seen)
    named = [r.getMessage() for r in caplog.records if "not in classes" in r.getMessage()]
    assert len(named) == 1 and named[0].count("'thing") == REPORTED_CLASSES
    assert len(seen) == REPORTED_CLASSES


def test_other_class_names_are_said_once_at_info(caplog):
    _, _, (pub_cloud, pub_dets) = _graph_node("filter")
    with caplog.at_level(logging.INFO):
        for k in (1, 2):
            cloud, dets = _messages(k * 1_000_000_000, labels=("Pedestrian", "Car"))
            pub_cloud.publish(cloud)
            pub_dets.publish(dets)
    lines = [r for r in caplog.records if "not in classes" in r.getMessage()]
    assert len(lines) == 1 and lines[0].levelno == logging.INFO and "passed on unjudged" in lines[0].getMessage()


def test_detections_without_hypotheses_are_said_and_can_be_included(caplog):
    graph, core, (pub_cloud, pub_dets) = _graph_node()
    completed = []
    LocalRuntime(graph, "probe").create_subscription("/completed", CLOUD, completed.append, RELIABLE)
    cloud, dets = _messages(1_000_000_000)
    for det in dets.detections:
        det.results = []  # a single-class detector that names no class
    with caplog.at_level(logging.WARNING):
        pub_cloud.publish(cloud)
        pub_dets.publish(dets)
    assert any("without a class" in r.getMessage() and "''" in r.getMessage() for r in caplog.records)
    assert read_xyz(completed[-1]).shape[0] == 0
    assert core.set_parameters({"classes": ["Car", "Van", ""]}).successful
    dets.header.stamp.sec = cloud.header.stamp.sec = 2
    pub_cloud.publish(cloud)
    pub_dets.publish(dets)
    assert set(read_xyz(completed[-1], ("instance",))[:, 3].tolist()) == {0.0, 1.0}


def test_detections_restamped_beyond_sync_slop_are_logged_with_the_gap(caplog):
    _, core, (pub_cloud, pub_dets) = _graph_node(sync_slop=0.05)
    with caplog.at_level(logging.WARNING):
        for k in (1, 2, 3):
            cloud, dets = _messages(k * 1_000_000_000, labels=("Car", "Car"),
                                    det_stamp_ns=k * 1_000_000_000 + 80_000_000)  # the detector's own clock
            pub_cloud.publish(cloud)
            pub_dets.publish(dets)
    assert core.frames == 0
    lines = [r.getMessage() for r in caplog.records if "sync_slop" in r.getMessage()]
    # the first drop is said (then the 10th, 100th ...) with why: the detections' stamp 80 ms off
    assert len(lines) == 1 and "scan stamped 1.000" in lines[0] and "80 ms away" in lines[0], lines
    values = core.diagnostics_values()
    assert int(values["dropped_clouds"]) >= 1 and values["last_unpaired_gap_ms"] == "80.0"


def test_scans_without_any_detections_name_the_topic_and_qos(caplog):
    _, core, (pub_cloud, _) = _graph_node()
    with caplog.at_level(logging.WARNING):
        for k in (1, 2, 3):  # the detector publishes best-effort: nothing reaches the reliable reader
            pub_cloud.publish(_messages(k * 1_000_000_000)[0])
    lines = [r.getMessage() for r in caplog.records if "dropped unpaired" in r.getMessage()]
    assert len(lines) == 1 and "'/detections'" in lines[0] and "qos.detections.reliability" in lines[0], lines
    assert core.diagnostics_values()["last_unpaired_gap_ms"] == "-"


@pytest.mark.parametrize("rule", ["evidence", "trapcc"])
def test_an_empty_or_all_nan_scan_rejects_nothing(rule, caplog):
    """A driver's empty cloud or an organized cloud all NaN (sensor blocked) holds no evidence:
    the detections pass unjudged (counted, logged), not all rejected for holding no returns."""
    _, boxes = _scene(("Car", "Car"))
    pipeline = Pipeline(PipelineConfig.from_dict({"backend": "mirror", "rule": rule}))
    dets = detection_array_from_boxes(boxes, "velodyne", 1_000_000_000)
    nan_grid = np.full((4, 8, 3), np.nan, np.float32)
    with caplog.at_level(logging.WARNING):
        for cloud in (create_cloud(np.zeros((0, 3), np.float32), ["x", "y", "z"], "velodyne", 1_000_000_000),
                      create_cloud(nan_grid, ["x", "y", "z"], "velodyne", 1_000_000_000)):
            result, originals = pipeline.process_messages(cloud, dets)
            assert list(result.status) == ["unjudged", "unjudged"] and result.skipped == {"empty scan": 2}
            assert not result.rejected and not len(result.completed_points)
            kept = build_outputs(result, originals)["detections_filtered"].detections
            assert [h.hypothesis.class_id for d in kept for h in d.results][-1] == UNJUDGED_CLASS_ID
    assert sum("no finite point" in r.getMessage() for r in caplog.records) == 1  # then every 100th


def test_a_leading_slash_in_the_detections_frame_names_the_scan_frame():
    _, core, (pub_cloud, pub_dets) = _graph_node()
    cloud, dets = _messages(1_000_000_000, labels=("Car", "Car"), det_frame="/velodyne")  # a ROS 1 driver / bag
    pub_cloud.publish(cloud)
    pub_dets.publish(dets)
    assert core.frames == 1 and core.no_transform == 0


def test_a_degenerate_box_in_every_frame_does_not_flood_the_log(monkeypatch, caplog):
    """A detector that sends one zero-size box per frame: the first 20 are logged one by one,
    then one line at every power of ten with the running count (at 10 Hz: not 10 lines a second)."""
    from pcc_ros.msg import detections as module

    monkeypatch.setattr(module, "_skipped", [0])
    _, boxes = _scene(("Car", "Car"))
    msg = detection_array_from_boxes(boxes, "velodyne", 0)
    msg.detections[1].bbox.size.x = 0.0
    with caplog.at_level(logging.WARNING):
        for _ in range(300):
            assert len(module.boxes_from_detection_array(msg, skip_invalid=True)) == 1
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("skipped detection 1")]
    assert len(lines) == 21 and "100 invalid boxes skipped so far" in lines[-1]


def test_the_count_of_skipped_boxes_not_logged_is_right_where_the_one_by_one_phase_ends(monkeypatch, caplog):
    """18 boxes already logged, then a message with 8 bad boxes: 2 are logged one by one (the
    19th and 20th), so the line after them names the other 6, not 8 - 5 = 3."""
    from pcc_ros.msg import detections as module

    monkeypatch.setattr(module, "_skipped", [18])
    boxes = Boxes(np.zeros((8, 3)), np.ones((8, 3)), np.zeros(8), ["Car"] * 8, np.full(8, 0.9), [""] * 8)
    msg = detection_array_from_boxes(boxes, "velodyne", 0)
    for det in msg.detections:
        det.bbox.size.x = 0.0
    with caplog.at_level(logging.WARNING):
        assert len(module.boxes_from_detection_array(msg, skip_invalid=True)) == 0
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("skipped")]
    assert len(lines) == 3 and lines[-1] == "skipped 6 more invalid detections in this message", lines


@pytest.mark.ros
def test_rclpy_node_maps_numeric_ids_and_logs_pipeline_skips_on_its_logger(shared_data, capfd, monkeypatch):
    """Real rclpy, real KITTI scan with its PointRCNN boxes labelled as OpenPCDet's wrapper labels
    them ('1'), one box of zero length: completed through class_map, and the skipped box is
    logged on the node's rclpy logger (node name, severity), not as bare stderr text."""
    require_rclpy()
    from sensor_msgs.msg import PointCloud2

    from pcc_ros.msg import detections as module

    monkeypatch.setattr(module, "_skipped", [0])  # skips of earlier tests do not count here
    from pcc_ros.data.kitti import KittiTracking
    from pcc_ros.nodes.ros_node import rclpy_classes

    root = shared_data / "kitti_tracking"
    frames = KittiTracking(root / "training").frames("0000", detections_dir=root / "detections" / "pointrcnn")
    frame = next(iter(frames))
    det = frame.detections
    size = det.size.copy()
    size[2, 0] = 0.0  # a degenerate box from the detector
    boxes = Boxes(det.center, det.size, det.yaw, ["1"] * len(det), det.score, det.track_id)
    stamp = 1_316_995_200_000_000_000
    cloud = create_cloud(frame.points, ["x", "y", "z", "intensity"], "velodyne", stamp, rclpy_classes)
    dets = detection_array_from_boxes(boxes, "velodyne", stamp, rclpy_classes)
    for det_msg, d in zip(dets.detections, size):
        det_msg.bbox.size.x = float(d[0])
    with live_pipeline_node("completion_node", "completion",
                            {"backend": "mirror", "class_map": "1:Car, 2:Pedestrian, 3:Cyclist"},
                            "completed", PointCloud2) as (node, exchange):
        got = exchange(cloud, dets, timeout=20)
        assert got, node.core.diagnostics_values()
        assert got[0].header.frame_id == "velodyne"
        instances = set(read_xyz(got[0], ("instance",))[:, 3].astype(int).tolist())
        assert instances and instances <= {0, 1}  # the two valid PointRCNN cars with points
        assert node.core.diagnostics_values().get("skipped_other_class") is None
        err = capfd.readouterr().err
        assert "[completion_node]: skipped detection 2" in err and "[WARN]" in err
