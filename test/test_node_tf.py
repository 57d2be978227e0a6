"""The node core with tf that lags, stalls, arrives late or jumps back, and the /diagnostics it publishes.

In-process graph (no middleware): a frame waits ``tf_timeout`` for its transform and is then
processed in the right place, or dropped and counted (never processed in the wrong frame); a
clock that jumps back resets pairing, queues and tf; the status turns WARN with the reason and
back; warnings name the resolved topic and check for publishers before blaming QoS. The same
behaviour under real rclpy: test/test_ros_tf.py.
"""

from __future__ import annotations

import logging
import time

import numpy as np
from shapes import box_surface

from pcc_ros.geometry.boxes import points_in_boxes
from pcc_ros.geometry.rotations import quaternion_from_yaw, rotation_z
from pcc_ros.geometry.transforms import Transform, transform_boxes
from pcc_ros.msg.detections import detection_array_from_boxes
from pcc_ros.msg.pointcloud2 import create_cloud, read_xyz
from pcc_ros.runtime.base import RELIABLE, SENSOR_DATA
from pcc_ros.runtime.local import LocalGraph, LocalRuntime
from pcc_ros.runtime.node import NodeCore
from pcc_ros.runtime.tf import TF_MESSAGE, TF_QOS, TransformListener
from pcc_ros.runtime.tfwait import TransformWait
from pcc_ros.types import Boxes

CLOUD, DETS = "sensor_msgs/msg/PointCloud2", "vision_msgs/msg/Detection3DArray"
DIAG = "diagnostic_msgs/msg/DiagnosticArray"
S = 1_000_000_000


def odom_from_velodyne(stamp_ns: int, yaw0: float = 0.4) -> Transform:
    """A vehicle driving and turning (the scan frame's pose in ``odom``)."""
    t = stamp_ns * 1e-9
    return Transform((2.0 + 8.0 * t, -1.0 + 1.5 * t, 1.7), tuple(quaternion_from_yaw(yaw0 + 0.3 * t).tolist()))


def scene(seed: int = 0):
    """Two cars (returns on their faces) and their boxes, in the velodyne frame."""
    rng = np.random.default_rng(seed)
    boxes = Boxes([[12.0, 1.0, -1.0], [7.0, -5.0, -0.9]], [[4.2, 1.8, 1.5], [4.4, 1.9, 1.6]], [0.3, -1.2],
                  ["Car", "Car"], [0.9, 0.8], ["a", "b"])
    cars = [box_surface(rng, 300, size / 2) @ rotation_z(yaw).T + center
            for center, size, yaw in zip(boxes.center, boxes.size, boxes.yaw)]
    ground = rng.uniform([0, -15, -1.8], [30, 15, -1.75], size=(300, 3))
    return np.concatenate([*cars, ground]).astype(np.float32), boxes


def pair_in_odom(stamp_ns: int, pose: Transform, classes=None):
    """The scan (velodyne) and its detections expressed in ``odom`` through ``pose`` (odom <- velodyne)."""
    points, boxes = scene()
    cloud = create_cloud(points, ["x", "y", "z"], "velodyne", stamp_ns, classes)
    dets = detection_array_from_boxes(transform_boxes(boxes, pose.matrix()), "odom", stamp_ns, classes)
    return cloud, dets


def assert_in_the_cars_boxes(msg) -> None:
    """Every completed point lies in its car's box in the scan frame (a wrong transform misses)."""
    _, boxes = scene()
    cloud = read_xyz(msg, ["instance"])
    assert len(cloud) > 100
    for i in np.unique(cloud[:, 3].astype(int)):
        pts = cloud[cloud[:, 3] == i, :3]
        inside = points_in_boxes(pts, boxes[np.array([i])], margin=0.2)[0]
        assert len(inside) >= 0.95 * len(pts), (i, len(inside), len(pts))


def completion_node(graph, **params) -> tuple[NodeCore, list, list]:
    core = NodeCore(LocalRuntime(graph, "completion_node"), "completion_node", "completion",
                    {"backend": "mirror", **params}, threaded=True)
    probe = LocalRuntime(graph, "probe")
    completed, diags = [], []
    probe.create_subscription("/completed", CLOUD, completed.append, RELIABLE)
    probe.create_subscription("/diagnostics", DIAG, diags.append, RELIABLE)
    return core, completed, diags


def publishers(graph):
    driver = LocalRuntime(graph, "driver")
    return (driver.create_publisher("/points", CLOUD, SENSOR_DATA),
            driver.create_publisher("/detections", DETS, RELIABLE))


def wait_until(predicate, timeout: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.01)
    return predicate()


def status(core):
    array = core.diagnostics_message()
    s = array.status[0]
    return int(s.level), s.message, {kv.key: kv.value for kv in s.values}


def test_a_frame_waits_for_its_transform_and_lands_in_the_right_place():
    graph = LocalGraph(simulated=True)
    core, completed, _ = completion_node(graph, tf_timeout=5.0)
    try:
        pub_cloud, pub_dets = publishers(graph)
        stamp = 10 * S
        pose = odom_from_velodyne(stamp)
        pub_cloud.publish(pair_in_odom(stamp, pose)[0])
        pub_dets.publish(pair_in_odom(stamp, pose)[1])
        assert wait_until(lambda: core.diagnostics_values()["frames_waiting_for_transform"] == "1")
        time.sleep(0.1)
        assert not completed  # held, not processed in the wrong frame
        # localisation catches up: samples around the stamp (interpolated, as tf2 does)
        for sample in (stamp - S // 20, stamp + S // 20):
            graph.transforms.set_transform("odom", "velodyne", odom_from_velodyne(sample), sample)
        assert wait_until(lambda: len(completed) == 1)
        assert_in_the_cars_boxes(completed[0])
        values = core.diagnostics_values()
        assert values["frames_released_after_waiting"] == "1" and values["frames_without_transform"] == "0"
        assert status(core)[0] == 0
    finally:
        core.shutdown()


def test_a_frame_whose_transform_never_comes_is_dropped_counted_and_the_node_recovers(caplog):
    graph = LocalGraph(simulated=True)
    core, completed, _ = completion_node(graph, tf_timeout=0.2)
    try:
        pub_cloud, pub_dets = publishers(graph)
        with caplog.at_level(logging.WARNING, logger="pcc_ros.completion_node"):
            cloud, dets = pair_in_odom(10 * S, odom_from_velodyne(10 * S))
            pub_cloud.publish(cloud)
            pub_dets.publish(dets)
            assert wait_until(lambda: core.no_transform == 1)
        assert not completed
        assert any("no transform 'odom' -> 'velodyne'" in r.getMessage() and "tf_timeout 0.2 s" in r.getMessage()
                   for r in caplog.records)
        level, message, values = status(core)
        assert level == 1 and "1 frame(s) dropped: no transform 'odom' -> 'velodyne'" in message
        assert values["frames_without_transform"] == "1" and values["frames_waiting_for_transform"] == "0"
        # tf back: the next frame is answered in the right place
        graph.transforms.set_transform("odom", "velodyne", odom_from_velodyne(11 * S))  # (static: any stamp)
        cloud, dets = pair_in_odom(11 * S, odom_from_velodyne(11 * S))
        pub_cloud.publish(cloud)
        pub_dets.publish(dets)
        assert wait_until(lambda: len(completed) == 1)
        assert_in_the_cars_boxes(completed[0])
        # the WARN lasts the window (10 s of node time), then the status is OK again
        graph.advance_to(25 * S)
        status(core)
        graph.advance_to(26 * S)
        assert status(core)[0] == 0
    finally:
        core.shutdown()


def test_a_newer_frame_whose_transform_arrived_drops_an_older_one_still_waiting():
    wait = TransformWait(timeout_s=10.0)
    for k in range(3):
        wait.add(("cloud", k))
    ready, dropped = wait.release(lambda pair: ("tf", "") if pair[1] == 1 else (None, f"missing {pair[1]}"))
    assert ready == [(("cloud", 1), "tf")] and dropped == [(("cloud", 0), "missing 0")] and len(wait) == 1
    assert [wait.add(("cloud", k)) for k in range(3, 11)][-1] == [("cloud", 2)]  # over capacity: the oldest goes


def test_a_clock_jump_back_resets_pairing_queues_and_tf_and_serves_the_new_timeline(caplog):
    graph = LocalGraph(simulated=True)
    core = NodeCore(LocalRuntime(graph, "completion_node"), "completion_node", "completion",
                    {"backend": "mirror"}, threaded=False)
    completed = []
    LocalRuntime(graph, "probe").create_subscription("/completed", CLOUD, completed.append, RELIABLE)
    pub_cloud, pub_dets = publishers(graph)
    graph.advance_to(10 * S)
    first = odom_from_velodyne(10 * S)
    for sample in (10 * S + k * S // 10 for k in range(-2, 3)):
        graph.transforms.set_transform("odom", "velodyne", odom_from_velodyne(sample), sample)
    cloud, dets = pair_in_odom(10 * S, first)
    pub_cloud.publish(cloud)
    pub_dets.publish(dets)
    assert len(completed) == 1
    pub_cloud.publish(pair_in_odom(10 * S + S // 10, first)[0])  # a scan of the old timeline, unpaired
    assert core.pairer.pending() == (1, 0)
    # The bag loops (or the simulator resets): the clock goes back to 9.9 s, and the same stamps
    # come again with the vehicle elsewhere (another yaw): the old tf samples would be wrong now.
    with caplog.at_level(logging.WARNING, logger="pcc_ros.completion_node"):
        graph.jump_to(9 * S + 9 * S // 10)
    assert core.pairer.pending() == (0, 0) and core.time_jumps == 1
    assert sum("clock jumped back" in r.getMessage() for r in caplog.records) == 1
    assert graph.transforms.lookup("odom", "velodyne", 10 * S) is None  # dynamic tf forgotten
    for k in range(-2, 3):
        stamp = 10 * S + k * S // 10
        graph.transforms.set_transform("odom", "velodyne", odom_from_velodyne(stamp, yaw0=2.0), stamp)
    graph.advance_to(10 * S)
    cloud, dets = pair_in_odom(10 * S, odom_from_velodyne(10 * S, yaw0=2.0))
    pub_cloud.publish(cloud)
    pub_dets.publish(dets)
    assert len(completed) == 2
    assert_in_the_cars_boxes(completed[1])
    level, message, values = status(core)
    assert level == 1 and "clock jumped back 1 time(s)" in message and values["time_jumps_back"] == "1"


def test_a_late_static_transform_is_picked_up_by_the_listener():
    """``/tf_static`` latched after the first scans: the listener's buffer answers from then on."""
    graph = LocalGraph(simulated=True)
    listener = TransformListener(LocalRuntime(graph, "listener"))
    driver = LocalRuntime(graph, "driver")
    from pcc_ros.data.bag_writer import tf_message
    from pcc_ros.runtime.tf import TF_STATIC_QOS

    assert listener.lookup("base_link", "velodyne", 5 * S) is None
    mount = Transform((0.8, 0.0, 1.7), tuple(quaternion_from_yaw(0.5).tolist()))
    driver.create_publisher("/tf_static", TF_MESSAGE, TF_STATIC_QOS).publish(
        tf_message([("base_link", "velodyne", mount.matrix())], 1 * S))
    np.testing.assert_allclose(listener.lookup("base_link", "velodyne", 5 * S).matrix(), mount.matrix(), atol=1e-12)
    listener.clear()  # a jump back keeps static transforms (tf2 does too)
    assert listener.lookup("base_link", "velodyne", 7 * S) is not None


def test_the_listener_keeps_ten_seconds_of_tf_not_the_whole_run():
    graph = LocalGraph(simulated=True)
    listener = TransformListener(LocalRuntime(graph, "listener"))
    from pcc_ros.data.bag_writer import tf_message

    pub = LocalRuntime(graph, "driver").create_publisher("/tf", TF_MESSAGE, TF_QOS)
    for k in range(3000):  # 100 s of /tf at 30 Hz
        stamp = k * S // 30
        pub.publish(tf_message([("odom", "base_link", odom_from_velodyne(stamp).matrix())], stamp))
    kept = listener.buffer.newest_stamp() - 99 * S
    assert listener.lookup("odom", "base_link", 95 * S) is not None
    assert listener.lookup("odom", "base_link", 80 * S) is None  # older than the 10 s cache
    assert kept >= 0
    assert sum(len(series.stamps) for series in vars(listener.buffer)["_dynamic"].values()) <= 11 * 30 + 32


def test_a_publisher_that_idled_is_not_reported_as_lost_scans(caplog):
    graph = LocalGraph(simulated=True)
    core, _, _ = completion_node(graph, scan_timeout=1.0)
    try:
        pub_cloud, pub_dets = publishers(graph)
        with caplog.at_level(logging.WARNING, logger="pcc_ros.completion_node"):
            for t in (1 * S, 64 * S):  # both publishers idle for a minute in between
                graph.advance_to(t)
                pub_dets.publish(pair_in_odom(t, odom_from_velodyne(t))[1])
                graph.advance_to(t + S // 20)
                pub_cloud.publish(pair_in_odom(t, odom_from_velodyne(t))[0])
        assert core.detections_without_scans == 0 and not core.scans_stalled
        assert not any("no scan" in r.getMessage() for r in caplog.records)
    finally:
        core.shutdown()


def test_warnings_name_the_resolved_topic_and_blame_qos_only_where_it_can_be_the_cause(caplog):
    graph = LocalGraph(simulated=True)
    runtime = LocalRuntime(graph, "completion_node", namespace="/car1")
    core = NodeCore(runtime, "completion_node", "completion", {"backend": "mirror", "scan_timeout": 0.5},
                    threaded=False, remap={"points": "lidar/points"})
    dets_pub = LocalRuntime(graph, "driver").create_publisher("/car1/detections", DETS, RELIABLE)
    with caplog.at_level(logging.WARNING, logger="pcc_ros.completion_node"):
        for k in range(12):
            graph.advance_to(k * S // 10)
            dets_pub.publish(pair_in_odom(k * S // 10, odom_from_velodyne(0))[1])
    text = "\n".join(r.getMessage() for r in caplog.records)
    assert "nobody publishes on '/car1/lidar/points'" in text, text
    assert "qos.points.reliability: best_effort" not in text  # already in force: never suggested
    caplog.clear()
    LocalRuntime(graph, "lidar").create_publisher("/car1/lidar/points", CLOUD, SENSOR_DATA)  # a publisher, but lost
    core.scans_stalled = False
    with caplog.at_level(logging.WARNING, logger="pcc_ros.completion_node"):
        for k in range(20, 28):
            graph.advance_to(k * S // 10)
            dets_pub.publish(pair_in_odom(k * S // 10, odom_from_velodyne(0))[1])
    text = "\n".join(r.getMessage() for r in caplog.records)
    assert "1 publisher(s) on '/car1/lidar/points' but nothing arrives" in text and "Large clouds" in text, text
    assert "best_effort" not in text
    level, message, _ = status(core)
    assert level == 1 and "no scan on '/car1/lidar/points'" in message


def test_a_street_over_max_crop_work_every_frame_is_logged_at_a_rate_not_every_frame(caplog):
    """A 128-beam scan of a busy street (260k points, 40 cars) exceeds the shipped max_crop_work in
    every frame (``pcc bench scale``): counted each frame, said for the 1st and every 100th, not 20
    lines a second."""
    from pcc_ros.pipeline.core import Pipeline, PipelineConfig

    pipeline = Pipeline(PipelineConfig(backend="mirror", max_crop_work=500))
    cloud, dets = pair_in_odom(S, Transform((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)))
    dets.header.frame_id = "velodyne"
    with caplog.at_level(logging.WARNING, logger="pcc_ros.pipeline.core"):
        skipped = [pipeline.process_messages(cloud, dets)[0].skipped.get("over max_crop_work", 0) for _ in range(12)]
    assert all(n >= 1 for n in skipped)
    lines = [r.getMessage() for r in caplog.records if "exceed max_crop_work" in r.getMessage()]
    assert len(lines) == 1 and "(1 such frames so far)" in lines[0]
