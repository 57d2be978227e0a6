"""NodeCore on the in-process runtime (no middleware): pairing, processing, publishing, diagnostics, bad input."""

from __future__ import annotations

import logging
import threading
import time

import numpy as np
import pytest
from conftest import require_rclpy

from pcc_ros.errors import ConfigError
from pcc_ros.msg.detections import boxes_from_detection_array, detection_array_from_boxes
from pcc_ros.msg.pointcloud2 import create_cloud, read_xyz
from pcc_ros.msg.typestore import get_typestore
from pcc_ros.pipeline.config import check_value, node_parameters, parameter_table, unknown_parameters
from pcc_ros.pipeline.core import Pipeline, PipelineConfig
from pcc_ros.pipeline.outputs import build_outputs
from pcc_ros.runtime.base import RELIABLE, SENSOR_DATA, QoS, Transform
from pcc_ros.runtime.local import LocalGraph, LocalRuntime
from pcc_ros.runtime.node import OUTPUTS, NodeCore, output_names, pipeline_stages
from pcc_ros.types import Boxes

CLOUD = "sensor_msgs/msg/PointCloud2"
DETS = "vision_msgs/msg/Detection3DArray"


def _scene(seed: int = 0):
    """Two cars with LiDAR-like returns on their visible sides (the faces towards the sensor at the
    origin: car a's rear, car b's rear and right side), one box with nothing in it."""
    rng = np.random.default_rng(seed)
    car1 = rng.uniform([-2, -0.85, -0.7], [-1.7, 0.85, 0.7], size=(400, 3)) + np.array([10, 0, -0.8])
    rear = rng.uniform([-2, -0.8, -0.7], [-1.7, 0.8, 0.7], size=(150, 3))
    side = rng.uniform([-2, -0.8, -0.7], [2, -0.5, 0.7], size=(150, 3))
    car2 = np.concatenate([rear, side]) + np.array([6, 5, -0.8])
    ground = rng.uniform([0, -10, -1.7], [30, 10, -1.6], size=(500, 3))
    points = np.concatenate([car1, car2, ground]).astype(np.float32)
    boxes = Boxes(
        [[10, 0, -0.8], [6, 5, -0.8], [20, -6, -0.8]],
        [[4.2, 1.8, 1.5], [4.2, 1.7, 1.5], [4.0, 1.7, 1.5]],
        [0.0, 0.1, 0.0],
        ["Car", "Car", "Car"],
        [0.9, 0.8, 0.2],
        ["a", "b", "c"],
    )
    return points, boxes


def _messages(stamp_ns: int, seed: int = 0, det_stamp_ns: int | None = None, frame: str = "velodyne"):
    points, boxes = _scene(seed)
    cloud = create_cloud(points, ["x", "y", "z"], "velodyne", stamp_ns)
    dets = detection_array_from_boxes(boxes, frame, stamp_ns if det_stamp_ns is None else det_stamp_ns)
    return cloud, dets


def _wire(msg, msgtype):
    return bytes(get_typestore().serialize_cdr(msg, msgtype))


@pytest.fixture
def graph():
    return LocalGraph(simulated=True)


def _node(graph, mode, threaded=False, **params):
    runtime = LocalRuntime(graph, f"{mode}_node")
    return NodeCore(runtime, f"{mode}_node", mode, {"backend": "mirror", **params}, threaded=threaded)


def _driver(graph):
    """A test driver's scan and detection publishers on ``graph``, with the nodes' QoS."""
    driver = LocalRuntime(graph, "driver")
    return (driver.create_publisher("/points", CLOUD, SENSOR_DATA),
            driver.create_publisher("/detections", DETS, RELIABLE))


def _send(driver, cloud, dets):
    """Publish one scan, then its detections, from ``driver``."""
    driver.create_publisher("/points", CLOUD, SENSOR_DATA).publish(cloud)
    driver.create_publisher("/detections", DETS, RELIABLE).publish(dets)


def _tap(graph, topic, msgtype, qos=RELIABLE):
    got = []
    LocalRuntime(graph, "probe").create_subscription(topic, msgtype, got.append, qos)
    return got


def test_completion_outputs_equal_the_pipeline_run_directly(graph):
    core = _node(graph, "completion")
    completed = _tap(graph, "/completed", CLOUD)
    markers = _tap(graph, "/completed_markers", "visualization_msgs/msg/MarkerArray")
    pub_cloud, pub_dets = _driver(graph)
    cloud, dets = _messages(1_000_000_000)
    pub_cloud.publish(cloud)
    assert not completed  # unpaired yet
    pub_dets.publish(dets)
    assert len(completed) == 1 and len(markers) == 1

    pipeline = Pipeline(PipelineConfig(backend="mirror"))
    result, originals = pipeline.process_messages(cloud, dets)
    expected = build_outputs(result, originals, detections_header=cloud.header)
    assert _wire(completed[0], CLOUD) == _wire(expected["completed"], CLOUD)
    out = read_xyz(completed[0], ("instance",))
    assert len(out) > 700 and set(np.unique(out[:, 3]).astype(int)) == {0, 1}  # the empty box is not completed
    assert core.frames == 1 and core.failures == 0


def test_marker_arrays_are_built_only_while_something_subscribes(graph, monkeypatch):
    """Markers are for a viewer: with no subscriber the node neither builds nor publishes them
    (most of the encode time with rclpy's classes); a viewer that subscribes gets the next frame's."""
    import pcc_ros.runtime.node as node_module

    asked = []
    build = node_module.build_outputs
    monkeypatch.setattr(node_module, "build_outputs",
                        lambda *a, names, **k: asked.append(sorted(names)) or build(*a, names=names, **k))
    core = _node(graph, "completion")
    completed = _tap(graph, "/completed", CLOUD)
    driver = LocalRuntime(graph, "driver")
    _send(driver, *_messages(1_000_000_000))
    assert len(completed) == 1 and asked == [["completed"]]
    assert core.publishers["completed_markers"].published == 0
    markers = _tap(graph, "/completed_markers", "visualization_msgs/msg/MarkerArray")
    _send(driver, *_messages(2_000_000_000))
    assert len(completed) == 2 and len(markers) == 1 and asked[1] == ["completed", "completed_markers"]


def test_filter_node_publishes_kept_and_rejected_and_markers(graph):
    core = _node(graph, "filter", match_threshold=0.3, detection_threshold=0.5)
    kept = _tap(graph, "/detections_filtered", DETS)
    rejected = _tap(graph, "/detections_rejected", DETS)
    markers = _tap(graph, "/filter_markers", "visualization_msgs/msg/MarkerArray")
    driver = LocalRuntime(graph, "driver")
    cloud, dets = _messages(2_000_000_000)
    driver.create_publisher("points", CLOUD, SENSOR_DATA).publish(cloud)
    driver.create_publisher("detections", DETS, RELIABLE).publish(dets)
    assert len(kept) == len(rejected) == len(markers) == 1
    ids_kept = [d.id for d in kept[0].detections]
    ids_rejected = [d.id for d in rejected[0].detections]
    # The empty low-score box "c" has maximal mismatch and a score under the threshold.
    assert "c" in ids_rejected and "a" in ids_kept
    assert sorted(ids_kept + ids_rejected) == ["a", "b", "c"]
    assert core.frames == 1


@pytest.mark.parametrize(("mode", "outputs"), [
    ("completion", None), ("filter", None), ("filter", output_names("filter", with_completion=True)),
])
def test_a_node_builds_only_what_it_publishes(graph, monkeypatch, mode, outputs):
    """Every published message equals the full build_outputs of the frame, and the outputs a node
    does not publish are never built: a completion node neither copies nor moves the detection
    messages (here in another frame than the scan), a filter node makes no completed cloud."""
    import pcc_ros.pipeline.core as core_module
    import pcc_ros.pipeline.outputs as outputs_module

    graph.set_transform("velodyne", "base_link", Transform((1.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)))
    cloud, dets = _messages(1_000_000_000, frame="base_link")
    transform = graph.transforms.lookup("velodyne", "base_link", 1_000_000_000)
    names = output_names(mode) if outputs is None else outputs
    # the stages the node runs for its outputs (a completion node judges nothing: its markers are grey)
    pipeline = Pipeline(PipelineConfig(backend="mirror"), **pipeline_stages(names))
    result, originals = pipeline.process_messages(cloud, dets, transform)
    expected = build_outputs(result, originals, detections_header=cloud.header)
    assert set(expected) == {*OUTPUTS["completion"], *OUTPUTS["filter"]}

    built: list[str] = []
    for module, name in ((core_module, "transform_detections"), (outputs_module, "completed_cloud_array"),
                         (outputs_module, "filter_texts")):
        original = getattr(module, name)
        monkeypatch.setattr(module, name, lambda *a, _f=original, _n=name, **k: built.append(_n) or _f(*a, **k))
    core = NodeCore(LocalRuntime(graph, f"{mode}_node"), f"{mode}_node", mode, {"backend": "mirror"}, threaded=False,
                    outputs=outputs)
    got = {name: _tap(graph, f"/{name}", msgtype) for name, msgtype in core.outputs.items()}
    _send(LocalRuntime(graph, "driver"), cloud, dets)
    assert core.frames == 1 and list(core.outputs) == names
    for name, msgtype in core.outputs.items():
        assert len(got[name]) == 1 and _wire(got[name][0], msgtype) == _wire(expected[name], msgtype), name
    assert ("transform_detections" in built) == ("detections_filtered" in names)
    assert ("completed_cloud_array" in built) == ("completed" in names)
    assert ("filter_texts" in built) == ("filter_markers" in names)


def test_pairing_respects_slop_and_counts_drops(graph):
    core = _node(graph, "completion", sync_slop=0.01, queue_size=2)
    completed = _tap(graph, "/completed", CLOUD)
    pub_cloud, pub_dets = _driver(graph)
    cloud, dets = _messages(1_000_000_000, det_stamp_ns=1_050_000_000)  # 50 ms apart > 10 ms slop
    pub_cloud.publish(cloud)
    pub_dets.publish(dets)
    assert not completed
    cloud2, dets2 = _messages(2_000_000_000, det_stamp_ns=2_005_000_000)  # 5 ms: pairs
    pub_cloud.publish(cloud2)
    pub_dets.publish(dets2)
    assert len(completed) == 1
    stats = core.pairer.stats
    assert stats.paired == 1 and stats.dropped_clouds == 1 and stats.dropped_detections == 1


def test_malformed_cloud_is_logged_skipped_and_the_node_keeps_serving(graph, caplog):
    core = _node(graph, "completion")
    completed = _tap(graph, "/completed", CLOUD)
    pub_cloud, pub_dets = _driver(graph)
    bad, dets = _messages(1_000_000_000)
    bad.width = bad.width + 1000  # claims more points than data holds
    with caplog.at_level(logging.WARNING, logger="pcc_ros.completion_node"):
        pub_cloud.publish(bad)
        pub_dets.publish(dets)
    assert not completed and core.failures == 1
    assert any("skipped a frame" in r.message and "PointCloud2" in r.message for r in caplog.records)
    good, dets = _messages(2_000_000_000)
    pub_cloud.publish(good)
    pub_dets.publish(dets)
    assert len(completed) == 1 and core.frames == 1


def test_worker_thread_processes_the_newest_pair(graph):
    wall = LocalGraph()  # wall clock: the timer and worker are real threads
    core = _node(wall, "completion", threaded=True)
    completed = _tap(wall, "/completed", CLOUD)
    pub_cloud, pub_dets = _driver(wall)
    try:
        for k in range(3):
            cloud, dets = _messages((k + 1) * 1_000_000_000, seed=k)
            pub_cloud.publish(cloud)
            pub_dets.publish(dets)
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and core.frames + core.pairer.stats.dropped_pairs < 3:
            time.sleep(0.02)
        assert core.frames >= 1
        assert core.frames + core.pairer.stats.dropped_pairs == 3  # each pair processed or counted as dropped
        from pcc_ros.msg.stamps import stamp_to_ns

        assert stamp_to_ns(completed[-1].header.stamp) == 3_000_000_000  # the newest always survives
    finally:
        core.shutdown()
        core.runtime.shutdown()


def test_diagnostics_follow_the_simulated_clock(graph):
    _node(graph, "completion")
    diags = _tap(graph, "/diagnostics", "diagnostic_msgs/msg/DiagnosticArray")
    driver = LocalRuntime(graph, "driver")
    cloud, dets = _messages(1_000_000_000)
    _send(driver, cloud, dets)
    graph.advance_to(2_500_000_000)
    assert len(diags) == 2
    status = diags[-1].status[0]
    values = {kv.key: kv.value for kv in status.values}
    assert values["frames"] == "1" and values["failed_frames"] == "0" and values["paired"] == "1"
    assert status.name == "pcc_ros: completion_node" and int(status.level) == 0
    assert diags[-1].header.stamp.sec == 2
    # The message is a valid DiagnosticArray on the wire.
    _wire(diags[-1], "diagnostic_msgs/msg/DiagnosticArray")


def test_detections_in_another_frame_go_through_the_runtime_transform(graph):
    core = _node(graph, "filter", rule="trapcc")  # the scene's ground shows through its cars
    kept = _tap(graph, "/detections_filtered", DETS)
    pub_cloud, pub_dets = _driver(graph)
    cloud, _ = _messages(1_000_000_000)
    _, boxes = _scene()
    shifted = Boxes(boxes.center - [1.0, 0.0, 0.0], boxes.size, boxes.yaw, boxes.label, boxes.score, boxes.track_id)
    dets = detection_array_from_boxes(shifted, "base_link", 1_000_000_000)
    pub_cloud.publish(cloud)
    pub_dets.publish(dets)
    assert not kept and core.no_transform == 1  # no transform known: logged once, skipped, counted
    assert core.diagnostics_values()["frames_without_transform"] == "1"
    graph.set_transform("velodyne", "base_link", Transform((1.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)))
    cloud, _ = _messages(2_000_000_000)
    dets = detection_array_from_boxes(shifted, "base_link", 2_000_000_000)
    pub_cloud.publish(cloud)
    pub_dets.publish(dets)
    assert len(kept) == 1
    moved = boxes_from_detection_array(kept[0])
    np.testing.assert_allclose(moved.center[:2], boxes.center[:2], atol=1e-6)


def test_qos_rule_best_effort_writer_never_reaches_reliable_reader(graph):
    got = _tap(graph, "/x", CLOUD, RELIABLE)
    cloud, _ = _messages(1)
    LocalRuntime(graph, "w").create_publisher("/x", CLOUD, SENSOR_DATA).publish(cloud)
    assert not got
    assert SENSOR_DATA.compatible_with_reader(QoS(reliable=False, depth=1))
    assert RELIABLE.compatible_with_reader(SENSOR_DATA)


def test_parameters_are_checked():
    with pytest.raises(ConfigError, match="unknown node parameter"):
        node_parameters({"backendd": "mirror"})
    with pytest.raises(ConfigError, match="mode"):
        NodeCore(LocalRuntime(LocalGraph(), "n"), "n", "completer", {"backend": "mirror"})
    values = node_parameters({"backend": "mirror", "use_sim_time": True})
    assert values["backend"] == "mirror" and values["sync_slop"] == 0.05


# ------------------------------------------------------------------ parameters (issue 21)


def test_unknown_and_bad_parameters_are_refused_with_the_name():
    with pytest.raises(ConfigError, match="'backendd'"):
        node_parameters({"backendd": "mirror"})
    with pytest.raises(ConfigError, match="'min_points' must be an integer"):
        node_parameters({"min_points": "many"})
    with pytest.raises(ConfigError, match=r"'match_threshold' = 1.5 is outside \[0.0, 1.0\]"):
        node_parameters({"match_threshold": 1.5})
    with pytest.raises(ConfigError, match=r"'qos\.points\.reliability' = 'sometimes' is not one of"):
        node_parameters({"qos.points.reliability": "sometimes"})
    # ROS's own and rclpy's QoS-override parameters are not ours to refuse
    assert unknown_parameters(["use_sim_time", "qos_overrides./points.subscription.depth", "x"]) == ["x"]
    assert node_parameters({"match_threshold": 1})["match_threshold"] == 1.0  # YAML's 1 for 1.0


def test_every_parameter_has_a_description_and_its_default_passes_its_own_rule():
    specs = parameter_table()
    for spec in specs:
        assert spec.description, spec.name
        check_value(spec, spec.default)
        if spec.range is not None:
            assert spec.type_name in ("integer", "double") and spec.constraints.startswith(str(spec.range[0]))
    names = {s.name for s in specs}
    assert {"output_frame", "half_precision", "class_thresholds", "qos.points.reliability"} <= names
    assert {s.name for s in specs if s.read_only} >= {"qos.points.depth", "qos.detections.reliability", "queue_size"}


def test_qos_parameters_reach_the_subscriptions_and_publishers(graph):
    core = _node(graph, "completion", **{"qos.points.reliability": "reliable", "qos.points.depth": 2,
                                         "qos.outputs.reliability": "best_effort", "qos.outputs.depth": 3})
    subs = {topic: s[0].qos for topic, s in graph._subs.items()}
    assert subs["/points"] == QoS(reliable=True, depth=2)
    assert subs["/detections"] == QoS(reliable=True, depth=10)
    assert core.publishers["completed"].qos == QoS(reliable=False, depth=3)
    # A reliable scan subscription no longer hears a best-effort (sensor-data) publisher.
    cloud, _ = _messages(1_000_000_000)
    LocalRuntime(graph, "driver").create_publisher("/points", CLOUD, SENSOR_DATA).publish(cloud)
    assert core.pairer.stats.paired == 0 and len(core.pairer._left) == 0


def test_set_parameters_swaps_thresholds_and_backend_without_dropping_the_node(graph):
    core = _node(graph, "filter", rule="trapcc")  # the TraPCC rule's thresholds (the scene is see-through)
    rejected = _tap(graph, "/detections_rejected", DETS)
    pub_cloud, pub_dets = _driver(graph)

    def frame(k):
        cloud, dets = _messages(k * 1_000_000_000)
        pub_cloud.publish(cloud)
        pub_dets.publish(dets)
        return [d.id for d in rejected[-1].detections]

    assert frame(1) == ["c"]  # the empty low-score (0.2) box
    completer = core.pipeline.completer
    assert core.set_parameters({"detection_threshold": 0.1}).successful
    assert core.pipeline.completer is completer  # thresholds swap without reloading the backend
    assert frame(2) == []  # 0.2 >= 0.1: kept by score alone
    # A bad value is refused with its reason and changes nothing.
    result = core.set_parameters({"detection_threshold": 0.9, "match_threshold": 7.0})
    assert not result.successful and "match_threshold" in result.reason
    assert core.parameters["detection_threshold"] == 0.1
    refused = core.set_parameters({"backend": "no_such_backend"})
    assert not refused.successful and "no_such_backend" in refused.reason
    assert core.pipeline.completer is completer
    assert not core.set_parameters({"qos.points.depth": 9}).successful  # read-only: restart the node
    import torch

    if not torch.cuda.is_available():  # a device that does not exist: refused, the old backend keeps serving
        refused = core.set_parameters({"backend": "pointpncnet", "device": "cuda:0"})
        assert not refused.successful and "CUDA is not available" in refused.reason
        assert core.pipeline.completer is completer and core.parameters["device"] == "auto"
    # A new backend loads and serves the next frame.
    assert core.set_parameters({"backend": "input", "detection_threshold": 0.5}).successful
    assert core.pipeline.completer.name == "input" and core.parameters["backend"] == "input"
    frame(3)
    assert core.frames == 3 and core.parameter_changes == 2
    values = {kv.key: kv.value for kv in core.diagnostics_message().status[0].values}
    assert values["backend"] == "input" and values["parameter_changes"] == "2"


def test_class_thresholds_override_the_detection_threshold_per_class(graph):
    with pytest.raises(ConfigError, match=r"'Car=0\.3'"):
        _node(graph, "filter", class_thresholds="Car=0.3")
    core = _node(graph, "filter", class_thresholds="Car:0.1", rule="trapcc")  # the TraPCC score gate
    rejected = _tap(graph, "/detections_rejected", DETS)
    driver = LocalRuntime(graph, "driver")
    cloud, dets = _messages(1_000_000_000)
    _send(driver, cloud, dets)
    assert rejected[-1].detections == []  # "c" scores 0.2 >= the Car threshold 0.1
    assert not core.set_parameters({"class_thresholds": "Car:2"}).successful
    assert core.set_parameters({"class_thresholds": "Van:0.1"}).successful
    cloud, dets = _messages(2_000_000_000)
    _send(driver, cloud, dets)
    assert [d.id for d in rejected[-1].detections] == ["c"]


def test_output_frame_moves_every_output_through_the_transform(graph):
    core = _node(graph, "filter", output_frame="map")
    kept = _tap(graph, "/detections_filtered", DETS)
    markers = _tap(graph, "/filter_markers", "visualization_msgs/msg/MarkerArray")
    pub_cloud, pub_dets = _driver(graph)
    cloud, dets = _messages(1_000_000_000)
    pub_cloud.publish(cloud)
    pub_dets.publish(dets)
    assert not kept and core.no_transform == 1  # no velodyne -> map yet: skipped and counted
    # map <- velodyne: 90 degrees about z, then 100 m along x
    quarter = (0.0, 0.0, np.sin(np.pi / 4), np.cos(np.pi / 4))
    graph.set_transform("map", "velodyne", Transform((100.0, 0.0, 0.0), quarter))
    cloud, dets = _messages(2_000_000_000)
    pub_cloud.publish(cloud)
    pub_dets.publish(dets)
    assert len(kept) == 1 and kept[0].header.frame_id == "map" and markers[-1].markers[1].header.frame_id == "map"
    moved = boxes_from_detection_array(kept[0])
    _, boxes = _scene()
    expected = np.c_[100.0 - boxes.center[:, 1], boxes.center[:, 0], boxes.center[:, 2]]
    index = {t: i for i, t in enumerate(boxes.track_id)}
    rows = [index[t] for t in moved.track_id]
    np.testing.assert_allclose(moved.center, expected[rows], atol=1e-6)
    np.testing.assert_allclose(np.cos(moved.yaw - boxes.yaw[rows] - np.pi / 2), 1.0, atol=1e-9)
    hypothesis = kept[0].detections[0].results[0].pose.pose.position
    assert (hypothesis.x, hypothesis.y) == pytest.approx(tuple(moved.center[0, :2]))


def test_output_frame_without_tf_says_so_once_and_counts_skipped_frames(graph, caplog):
    runtime = LocalRuntime(graph, "filter_node")
    runtime.has_tf = False  # what the rclpy host reports with neither tf2_ros nor tf2_msgs installed
    with caplog.at_level(logging.ERROR, logger="pcc_ros.filter_node"):
        core = NodeCore(runtime, "filter_node", "filter", {"backend": "mirror", "output_frame": "map"}, threaded=False)
    assert sum("needs transforms" in r.message for r in caplog.records) == 1
    driver = LocalRuntime(graph, "driver")
    for k in (1, 2):
        cloud, dets = _messages(k * 1_000_000_000)
        _send(driver, cloud, dets)
    values = core.diagnostics_values()
    assert values["frames_without_transform"] == "2" and values["frames"] == "0"


def test_completed_cloud_carries_instance_source_colour_and_score(graph):
    _node(graph, "completion", include_observed_points=True)
    completed = _tap(graph, "/completed", CLOUD)
    driver = LocalRuntime(graph, "driver")
    cloud, dets = _messages(1_000_000_000)
    _send(driver, cloud, dets)
    from pcc_ros.msg.pointcloud2 import structured_view

    points = structured_view(completed[0])
    assert [f.name for f in completed[0].fields] == ["x", "y", "z", "instance", "rgb", "score", "source"]
    for instance, score in ((0, 0.9), (1, 0.8)):
        mine = points[points["instance"] == instance]
        observed = mine[mine["source"] == 0]
        made = mine[mine["source"] == 1]
        assert len(observed) >= 250 and len(made) > 0  # the car's own returns and the backend's points
        assert np.all(mine["score"] == np.float32(score))
        assert len(np.unique(mine["rgb"].view(np.uint32))) == 1
    colours = {int(points["rgb"].view(np.uint32)[points["instance"] == i][0]) for i in (0, 1)}
    assert len(colours) == 2  # one colour per instance


def test_filter_markers_read_the_mapped_score_mismatch_and_decision(graph):
    _node(graph, "filter", score_mapping="sigmoid", detection_threshold=0.6, rule="trapcc")
    markers = _tap(graph, "/filter_markers", "visualization_msgs/msg/MarkerArray")
    driver = LocalRuntime(graph, "driver")
    cloud, dets = _messages(1_000_000_000)
    _send(driver, cloud, dets)
    texts = [m.text for m in markers[0].markers if m.ns.endswith("_text")]
    assert len(texts) == 3
    assert texts[2] == "Car p=0.55 m=1.00 rejected"  # sigmoid(0.2) = 0.55 < 0.6, empty box
    assert texts[0].startswith("Car p=0.71 m=") and texts[0].endswith(" kept")


def test_docs_show_the_parameter_table_as_the_code_defines_it():
    from pathlib import Path

    from pcc_ros.pipeline.config import markdown_table

    doc = (Path(__file__).resolve().parents[1] / "docs" / "nodes.md").read_text()
    assert markdown_table() in doc, "docs/nodes.md is out of date: paste pcc_ros.pipeline.config.markdown_table()"


def test_half_precision_runs_the_shipped_network_under_autocast():
    points, boxes = _scene()
    full = Pipeline(PipelineConfig(backend="pointpncnet", device="cpu"))
    half = Pipeline(PipelineConfig(backend="pointpncnet", device="cpu", half_precision=True))
    assert half.completer.half_precision and not full.completer.half_precision
    a, b = full.process(points, boxes), half.process(points, boxes)
    assert a.completed_points.shape == b.completed_points.shape
    assert not np.array_equal(a.completed_points, b.completed_points)  # really ran in bfloat16
    # bfloat16 keeps ~3 significant digits: the completed cars agree to millimetres (median)
    assert np.median(np.abs(a.completed_points - b.completed_points)) < 0.01


# ------------------------------------------------------------------ scans that stop arriving (issue 13)


def test_scan_timeout_must_be_positive():
    with pytest.raises(ConfigError, match="scan_timeout"):
        _node(LocalGraph(simulated=True), "completion", scan_timeout=0.0)


def test_detections_without_scans_are_counted_and_reported(graph, caplog):
    core = _node(graph, "completion", scan_timeout=0.5)
    diags = _tap(graph, "/diagnostics", "diagnostic_msgs/msg/DiagnosticArray")
    pub_cloud, pub_dets = _driver(graph)
    cloud, dets = _messages(1_000_000_000)
    graph.advance_to(1_000_000_000)
    pub_cloud.publish(cloud)
    pub_dets.publish(dets)
    # Scans stop (a 2 MB cloud the middleware drops); detections keep coming at 10 Hz.
    with caplog.at_level(logging.WARNING):
        for i in range(1, 21):
            stamp = 1_000_000_000 + i * 100_000_000
            graph.advance_to(stamp)
            pub_dets.publish(_messages(stamp)[1])
    assert core.scans == 1 and core.detection_arrays == 21
    assert core.detections_without_scans == 15  # those more than 0.5 s after the last scan
    assert core.scans_stalled
    assert sum("no scan on '/points'" in r.getMessage() for r in caplog.records) == 1  # warned once
    status = diags[-1].status[0]  # published at 3.0 s by the 1 Hz timer
    assert int(status.level) == 1 and "no scan" in status.message
    values = core.diagnostics_values()
    assert values["detections_without_scans"] == "15" and values["scans_received"] == "1"
    graph.advance_to(3_100_000_000)
    pub_cloud.publish(_messages(3_100_000_000)[0])  # scans are back: the warning clears
    assert not core.scans_stalled
    graph.advance_to(4_000_000_000)
    assert int(diags[-1].status[0].level) == 0


# ------------------------------------------------------------------ under real rclpy


def test_rclpy_node_declares_rules_refuses_unknown_keys_and_swaps_at_run_time():
    rclpy = require_rclpy()  # make setup installs ROS 2 (vision_msgs built): this test runs, never skips
    from rclpy.parameter import Parameter

    from pcc_ros.nodes.ros_node import PipelineNode

    rclpy.init()
    nodes = []
    try:
        with pytest.raises(ConfigError, match=r"unknown node parameter\(s\): \['backendd'\]"):
            PipelineNode("filter_node", "filter", parameter_overrides=[Parameter("backendd", value="mirror")])
        with pytest.raises(ConfigError, match="'match_threshold'"):
            PipelineNode("filter_node", "filter", parameter_overrides=[Parameter("match_threshold", value=3.0)])
        node = PipelineNode("filter_node", "filter", parameter_overrides=[Parameter("backend", value="mirror"),
                                                                         Parameter("rule", value="trapcc")])
        nodes.append(node)
        described = node.describe_parameters(["match_threshold", "min_points", "qos.points.depth"])
        assert described[0].floating_point_range[0].to_value == 1.0 and described[0].description
        assert described[1].integer_range[0].from_value == 1
        assert described[2].read_only
        result = node.set_parameters([Parameter("match_threshold", value=7.0)])[0]
        assert not result.successful and "match_threshold" in result.reason
        result = node.set_parameters([Parameter("backend", value="no_such_backend")])[0]
        assert not result.successful and "no_such_backend" in result.reason
        assert node.get_parameter("backend").value == "mirror" and node.core.pipeline.completer.name == "mirror"
        assert not node.set_parameters([Parameter("qos.points.depth", value=3)])[0].successful
        ok = node.set_parameters([Parameter("backend", value="input"), Parameter("detection_threshold", value=0.4)])
        assert all(r.successful for r in ok)
        assert node.core.pipeline.completer.name == "input" and node.core.parameters["detection_threshold"] == 0.4
    finally:
        for node in nodes:
            node.destroy_node()
        rclpy.try_shutdown()


def test_replay_config_is_checked_as_the_nodes_check_it(tmp_path):
    from pcc_ros.pipeline.config import load_config

    typo = tmp_path / "typo.yaml"
    typo.write_text("/**/detection_filter_node:\n  ros__parameters:\n    backendd: mirror\n")
    with pytest.raises(ConfigError, match=r"typo\.yaml: unknown node parameter\(s\): \['backendd'\]"):
        load_config(typo, True)
    config, slop = load_config(None, True, backend="mirror", score_mapping="sigmoid")
    assert config.filter.score_mapping == "sigmoid" and config.backend == "mirror" and slop == 0.05


def test_a_running_node_keeps_its_start_up_objects_out_of_full_collections(graph):
    """Start-up objects are frozen (a full collection never walks them during a frame: the stall
    ``pcc_ros.runtime.heap`` describes); a backend reloaded at run time frees the old one, reference
    cycles included, instead of keeping it frozen forever."""
    import gc
    import weakref

    gc.unfreeze()
    core = _node(graph, "completion")
    assert gc.get_freeze_count() > 0
    old = core.pipeline
    old.cycle = old  # a reference cycle: only the collector frees it, and never while frozen
    gone = weakref.ref(old)
    del old
    assert core.set_parameters({"backend": "input"}).successful
    assert gone() is None and core.pipeline.completer.name == "input"
    assert gc.get_freeze_count() > 0


def test_a_threaded_node_collects_a_reloaded_backend_between_frames(graph):
    """A backend reloaded while a frame runs on it: the worker collects after that frame, so the
    old backend (a reference cycle here) is freed; collected and frozen at once instead, the
    frame's reference would have kept it alive through the collection and frozen for good."""
    import gc
    import weakref

    core = _node(LocalGraph(), "completion", threaded=True)
    started, release = threading.Event(), threading.Event()

    def frame_on_the_old_backend(cloud, dets, transforms=None):
        held = core.pipeline  # what process() holds during a frame
        started.set()
        release.wait(5)
        del held

    try:
        core.process = frame_on_the_old_backend
        old = core.pipeline
        old.cycle = old
        gone = weakref.ref(old)
        del old
        core.slot.put((None, None))
        assert started.wait(5)
        assert core.set_parameters({"backend": "input"}).successful
        release.set()
        deadline = time.monotonic() + 5  # the worker wakes within its 0.5 s wait
        while time.monotonic() < deadline and (gone() is not None or not gc.get_freeze_count()):
            time.sleep(0.02)  # (between the worker's collect and its freeze, nothing is frozen)
        assert gone() is None and gc.get_freeze_count() > 0
        assert core.pipeline.completer.name == "input"
    finally:
        release.set()
        core.shutdown()
        core.runtime.shutdown()


def test_a_node_core_dropped_earlier_is_not_frozen_by_the_next_ones_start_up():
    """A node core is a reference cycle (its graph's subscriptions hold its bound methods), so a
    dropped one waits for the collector; the next core's start-up freeze must not keep it (and
    its pipeline) for good: the test suite and ``pcc demo`` build many cores in one process."""
    import gc
    import weakref

    first = _node(LocalGraph(simulated=True), "completion")  # its graph goes with it
    gone = weakref.ref(first.pipeline)
    del first
    _node(LocalGraph(simulated=True), "completion")
    gc.collect()
    assert gone() is None


def test_a_nodes_log_lines_keep_their_module_name_and_carry_the_node():
    """While a node core works, the package's records keep their module's name (a logging filter
    by module still selects them) and carry the node's (``pcc_node``), which pcc's console shows
    in the name's place; a record made by hand (``makeLogRecord``, no name) is left alone."""
    import logging

    from pcc_ros.cli.main import NodeNameFormatter
    from pcc_ros.runtime.node import working_for

    class Node:
        name = "pcc_ros.completion_node"

    seen = []

    class Keep(logging.Handler):
        def emit(self, record):
            seen.append(record)

    handler, package = Keep(), logging.getLogger("pcc_ros")
    handler.addFilter(logging.Filter("pcc_ros.pipeline"))
    package.addHandler(handler)
    try:
        with working_for(Node()):
            logging.getLogger("pcc_ros.pipeline.core").warning("a pipeline line")
            assert not hasattr(logging.makeLogRecord({"msg": "by hand"}), "pcc_node")
    finally:
        package.removeHandler(handler)
    assert [(r.name, r.pcc_node) for r in seen] == [("pcc_ros.pipeline.core", "pcc_ros.completion_node")]
    assert NodeNameFormatter().format(seen[0]) == "WARNING pcc_ros.completion_node: a pipeline line"
    assert seen[0].name == "pcc_ros.pipeline.core"  # formatting did not rename it


def test_each_node_runs_only_the_stages_its_outputs_and_rule_need(graph):
    """The filter node with a rule that gives the shape no weight (the shipped file: evidence rule,
    w_mismatch 0) loads no completion backend and runs no network, though its file names the
    trained one; the completion node runs no filter. A change to a rule that scores the shape
    loads the backend then (and only then)."""
    from pcc_ros.pipeline.config import load_parameters

    values = load_parameters(with_filter=True)
    assert values["rule"] == "evidence" and values["w_mismatch"] == 0.0 and values["backend"] == "pointpncnet"
    filter_core = NodeCore(LocalRuntime(graph, "detection_filter_node"), "detection_filter_node", "filter", values,
                           threaded=False)
    completion_core = _node(graph, "completion")
    results = {}
    filter_core.on_result = lambda result, *_: results.setdefault("filter", result)
    completion_core.on_result = lambda result, *_: results.setdefault("completion", result)
    kept = _tap(graph, "/detections_filtered", DETS)
    completed = _tap(graph, "/completed", CLOUD)
    _send(LocalRuntime(graph, "driver"), *_messages(1_000_000_000))
    assert len(kept) == 1 and len(completed) == 1

    assert filter_core.pipeline.completer is None and not filter_core.pipeline.completes
    judged = results["filter"]
    assert "complete_ms" not in judged.timings_ms and judged.completions == [] and judged.crops == []
    assert set(judged.status) <= {"kept", "rejected"} and np.isfinite(judged.filter_score).all()
    assert judged.completed_source.tolist() == [] or (judged.completed_source == 0).all()  # nothing generated

    assert not completion_core.pipeline.filters and completion_core.pipeline.completer is not None
    made = results["completion"]
    assert "filter_ms" not in made.timings_ms and set(made.status) == {"skipped"}  # not judged
    assert len(made.completions) == 2 and np.isnan(made.filter_score).all()

    # the same filter node asked to weigh the shape: the backend loads (mirror: cheap) and runs
    assert filter_core.set_parameters({"w_mismatch": 0.5, "trees": "", "backend": "mirror"}).successful
    assert filter_core.pipeline.completer is not None
    results.clear()
    _send(LocalRuntime(graph, "driver"), *_messages(2_000_000_000))
    assert "complete_ms" in results["filter"].timings_ms and len(results["filter"].completions) == 2


def test_qos_overrides_are_honoured_or_refused_under_rclpy():
    """rclpy's ``qos_overrides.<topic>.<entity>.<policy>`` parameters set the entity's QoS (here the
    scan subscription made reliable, as the graph reports it); one that names no topic, entity or
    policy of the node, or a value rclpy does not know, stops the node with the name (it used to
    be accepted and ignored)."""
    rclpy = require_rclpy()
    from rclpy.parameter import Parameter
    from rclpy.qos import ReliabilityPolicy

    from pcc_ros.nodes.ros_node import PipelineNode

    rclpy.init()
    nodes = []
    try:
        for name, value, match in (("qos_overrides./point.subscription.reliability", "reliable", "/point.subscription"),
                                   ("qos_overrides./points.subscription.durability", "volatile", "durability"),
                                   ("qos_overrides./points.subscription.reliability", "sometimes", "sometimes")):
            with pytest.raises(ConfigError, match=match):
                PipelineNode("completion_node", "completion",
                             parameter_overrides=[Parameter("backend", value="mirror"), Parameter(name, value=value)])
        node = PipelineNode("completion_node", "completion", parameter_overrides=[
            Parameter("backend", value="mirror"),
            Parameter("qos_overrides./points.subscription.reliability", value="reliable"),
            Parameter("qos_overrides./completed.publisher.depth", value=3)])
        nodes.append(node)
        assert node.core.parameters["qos.points.reliability"] == "best_effort"  # the node's own default ...
        (info,) = node.get_subscriptions_info_by_topic("/points")
        assert info.qos_profile.reliability == ReliabilityPolicy.RELIABLE  # ... overridden
        assert node.get_parameter("qos_overrides./completed.publisher.depth").value == 3
    finally:
        for node in nodes:
            node.destroy_node()
        rclpy.try_shutdown()


def test_a_frame_still_running_when_serving_stops_is_never_published(monkeypatch, caplog):
    """Stopping (a managed node's deactivate, or exit) waits a bounded time for the frame in
    flight; a frame that outlasts the wait finds no publisher and is dropped, so nothing is ever
    published on a publisher the runtime is about to destroy."""
    import pcc_ros.runtime.node as node_module

    monkeypatch.setattr(node_module, "STOP_WAIT_S", 0.05)
    wall = LocalGraph()
    core = _node(wall, "completion", threaded=True)
    completed = _tap(wall, "/completed", CLOUD)
    started, release = threading.Event(), threading.Event()
    process_messages = core.pipeline.process_messages

    def slow_frame(*args, **kwargs):
        started.set()
        release.wait(5)
        return process_messages(*args, **kwargs)

    core.pipeline.process_messages = slow_frame
    worker = core._worker
    try:
        pub_cloud, pub_dets = _driver(wall)
        cloud, dets = _messages(1_000_000_000)
        pub_cloud.publish(cloud)
        pub_dets.publish(dets)
        assert started.wait(5)
        with caplog.at_level(logging.WARNING):
            core.shutdown()  # returns after the short wait, the frame still running
        assert worker.is_alive()
        assert any("still runs" in r.message for r in caplog.records)
        release.set()
        worker.join(5)
        assert not worker.is_alive()
        assert completed == [] and core.frames == 0
    finally:
        release.set()
        core.shutdown()
        core.runtime.shutdown()
