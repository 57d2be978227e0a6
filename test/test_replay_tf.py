"""Offline == online with tf: ``pcc replay`` over a bag whose detections are in another frame.

The detections are in ``odom``; the scan is in ``velodyne``; ``/tf`` carries a moving, yawing
``odom <- base_link`` sampled between the scans' stamps (interpolated, as tf2 does) and
``/tf_static`` a yawed ``base_link <- velodyne`` mount. ``pcc replay`` must record exactly
(CDR byte for byte) what the completion and filter node cores publish for the same messages
with the same transforms, and every completed point must land in its car's box in the scan
frame (a transform applied with the wrong sign, order or yaw puts it elsewhere).
"""

from __future__ import annotations

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from shapes import box_surface

from pcc_ros.cli.main import main as pcc
from pcc_ros.data.bag import ReadStats, read_frames
from pcc_ros.data.bag_writer import atomic_bag, tf_message
from pcc_ros.geometry.boxes import points_in_boxes
from pcc_ros.geometry.rotations import quaternion_from_yaw, rotation_z
from pcc_ros.geometry.transforms import Transform, transform_boxes
from pcc_ros.msg.detections import boxes_from_detection_array, detection_array_from_boxes
from pcc_ros.msg.pointcloud2 import create_cloud, read_xyz
from pcc_ros.msg.tf_buffer import TransformBuffer
from pcc_ros.msg.typestore import get_typestore
from pcc_ros.pipeline.config import load_parameters
from pcc_ros.runtime.base import RELIABLE, SENSOR_DATA
from pcc_ros.runtime.local import LocalGraph, LocalRuntime
from pcc_ros.runtime.node import NodeCore, output_names
from pcc_ros.types import Boxes

CLOUD, DETS, TF = "sensor_msgs/msg/PointCloud2", "vision_msgs/msg/Detection3DArray", "tf2_msgs/msg/TFMessage"
STAMPS = [1_000_000_000, 1_100_000_000, 1_200_000_000]
#: base_link <- velodyne: the LiDAR mounted 1.7 m up, 0.8 m forward, turned 35 degrees.
MOUNT = Transform((0.8, 0.3, 1.7), tuple(quaternion_from_yaw(np.radians(35.0)).tolist()))


def odom_from_base(stamp_ns: int) -> Transform:
    """The vehicle's pose: constant velocity and yaw rate (so tf2's interpolation is exact)."""
    t = stamp_ns * 1e-9
    return Transform((2.0 + 8.0 * t, -1.0 + 1.5 * t, 0.0), tuple(quaternion_from_yaw(0.4 + 0.3 * t).tolist()))


def scene(seed: int):
    """Three cars (returns on their faces) and the boxes, in the velodyne frame."""
    rng = np.random.default_rng(seed)
    boxes = Boxes(
        [[12.0, 1.0, -1.0], [7.0, -5.0, -0.9], [20.0, 6.0, -1.0]],
        [[4.2, 1.8, 1.5], [4.4, 1.9, 1.6], [4.0, 1.7, 1.5]],
        [0.3, -1.2, 2.5],
        ["Car", "Car", "Car"],
        [0.9, 0.8, 0.7],
        ["a", "b", "c"],
    )
    cars = [
        box_surface(rng, 400, size / 2) @ rotation_z(yaw).T + center
        for center, size, yaw in zip(boxes.center, boxes.size, boxes.yaw)
    ]
    ground = rng.uniform([0, -15, -1.8], [30, 15, -1.75], size=(600, 3))
    return np.concatenate([*cars, ground]).astype(np.float32), boxes


def messages():
    """``(bag time, topic, type, message)`` in time order: tf every 30 ms, three scan/detection pairs."""
    out = [(STAMPS[0] - 50_000_000, "/tf_static", TF,
            tf_message([("base_link", "velodyne", MOUNT.matrix())], STAMPS[0] - 50_000_000))]
    for stamp in range(STAMPS[0] - 45_000_000, STAMPS[-1] + 60_000_000, 30_000_000):
        out.append((stamp, "/tf", TF, tf_message([("odom", "base_link", odom_from_base(stamp).matrix())], stamp)))
    for k, stamp in enumerate(STAMPS):
        points, boxes = scene(k)
        velodyne_to_odom = (odom_from_base(stamp) @ MOUNT).matrix()  # odom <- velodyne at the scan's stamp
        in_odom = transform_boxes(boxes, velodyne_to_odom)
        out.append((stamp, "/points", CLOUD, create_cloud(points, ["x", "y", "z"], "velodyne", stamp)))
        out.append((stamp + 1_000_000, "/detections", DETS, detection_array_from_boxes(in_odom, "odom", stamp)))
    return sorted(out, key=lambda item: item[0])


@pytest.fixture(scope="module")
def bag(tmp_path_factory):
    path = tmp_path_factory.mktemp("tf") / "yawed"
    with atomic_bag(path) as writer:
        for time_ns, topic, msgtype, msg in messages():
            writer.write(topic, msgtype, msg, time_ns)
    return path


def read_raw(bag) -> dict[str, list[bytes]]:
    with AnyReader([bag], default_typestore=get_typestore()) as reader:
        out: dict[str, list[bytes]] = {}
        for connection, _, raw in reader.messages():
            out.setdefault(connection.topic, []).append(bytes(raw))
        return out


def live(mode: str) -> dict[str, list[bytes]]:
    """What a node core of ``mode`` publishes on a graph carrying the same messages and transforms."""
    graph = LocalGraph(simulated=True)
    graph.advance_to(STAMPS[0] - 100_000_000)
    name = {"completion": "completion_node", "filter": "detection_filter_node"}[mode]
    core = NodeCore(LocalRuntime(graph, name), name, mode, load_parameters(None, mode == "filter", backend="mirror"),
                    threaded=False)
    got: dict[str, list[bytes]] = {}
    probe = LocalRuntime(graph, "probe")
    store = get_typestore()
    for topic, msgtype in core.outputs.items():
        probe.create_subscription(
            topic, msgtype, lambda m, t=topic, ty=msgtype: got.setdefault(f"/{t}", []).append(
                bytes(store.serialize_cdr(m, ty))), SENSOR_DATA)
    publishers = {"/points": probe.create_publisher("/points", CLOUD, SENSOR_DATA),
                  "/detections": probe.create_publisher("/detections", DETS, RELIABLE)}
    # tf2's listener has every transform a lookup needs by the time it is made (it waits up to
    # 50 ms for the sample after the stamp); the buffer is filled first, as replay fills it.
    for _, topic, _, msg in messages():
        if topic in ("/tf", "/tf_static"):
            graph.transforms.add_message(msg, static=topic == "/tf_static")
    for time_ns, topic, _, msg in messages():
        graph.advance_to(time_ns)
        if topic in publishers:
            publishers[topic].publish(msg)
    assert core.frames == len(STAMPS) and core.failures == 0
    return got


@pytest.mark.parametrize("mode", ["completion", "filter"])
def test_replay_equals_the_node_core_with_a_yawed_transform(bag, tmp_path, mode):
    out = tmp_path / mode
    flags = ["--filter"] if mode == "filter" else []
    assert pcc(["replay", str(bag), "--out", str(out), "--backend", "mirror", "--no-copy-inputs", *flags]) == 0
    recorded = read_raw(out)
    expected = live(mode)
    assert set(output_names(mode)) <= {t.lstrip("/") for t in recorded}
    for topic, messages_ in expected.items():
        assert len(messages_) == len(STAMPS), topic
        assert recorded[topic] == messages_, topic  # byte for byte


def test_completed_points_land_in_the_correctly_transformed_boxes(bag, tmp_path):
    out = tmp_path / "filter"
    assert pcc(["replay", str(bag), "--out", str(out), "--backend", "mirror", "--filter", "--no-copy-inputs"]) == 0
    store = get_typestore()
    with AnyReader([out], default_typestore=store) as reader:
        by_topic: dict[str, list] = {}
        for connection, _, raw in reader.messages():
            by_topic.setdefault(connection.topic, []).append(reader.deserialize(raw, connection.msgtype))
    for k, cloud in enumerate(by_topic["/completed"]):
        _, truth = scene(k)
        assert cloud.header.frame_id == "velodyne"
        points = read_xyz(cloud, ("instance",))
        assert set(np.unique(points[:, 3]).astype(int)) == {0, 1, 2}  # every car completed
        decided = [boxes_from_detection_array(by_topic[t][k]) for t in ("/detections_filtered", "/detections_rejected")]
        published = Boxes.concatenate(decided)
        order = np.argsort(published.track_id)
        np.testing.assert_allclose(published.center[order], truth.center, atol=1e-6)
        np.testing.assert_allclose(np.cos(published.yaw[order] - truth.yaw), 1.0, atol=1e-9)
        for i in range(len(truth)):
            mine = points[points[:, 3] == i, :3]
            inside = points_in_boxes(mine, truth[[i]], margin=0.15)[0]
            assert len(mine) > 100 and len(inside) == len(mine), (k, i, len(mine) - len(inside))


def test_read_frames_moves_boxes_into_the_scan_frame_and_takes_the_pose_from_the_tf_tree(bag):
    """The offline reader takes the node's tf path too: boxes stamped in odom come out in the
    scan's frame (moved at their stamp, as replay and a live node move them), the pose is
    odom <- velodyne interpolated between the /tf samples around the scan, and the static
    mount is the frame's sensor_to_base."""
    frames = list(read_frames(bag))
    assert [f.stamp_ns for f in frames] == STAMPS
    for k, frame in enumerate(frames):
        _, truth = scene(k)
        assert frame.frame_id == "velodyne"
        np.testing.assert_allclose(frame.detections.center, truth.center, atol=1e-9)
        np.testing.assert_allclose(np.cos(frame.detections.yaw - truth.yaw), 1.0, atol=1e-12)
        np.testing.assert_allclose(frame.pose, (odom_from_base(STAMPS[k]) @ MOUNT).matrix(), atol=1e-9)
        np.testing.assert_allclose(frame.extras["sensor_to_base"], MOUNT.matrix(), atol=1e-12)


def test_read_frames_skips_a_frame_whose_boxes_cannot_be_moved(tmp_path):
    """Boxes in a frame the tf tree does not reach: that frame is skipped and counted, not read in the wrong frame."""
    path = tmp_path / "no_tf"
    points, boxes = scene(0)
    with atomic_bag(path) as writer:
        for k, stamp in enumerate(STAMPS[:2]):
            writer.write("/points", CLOUD, create_cloud(points, ["x", "y", "z"], "velodyne", stamp), stamp)
            writer.write("/detections", DETS, detection_array_from_boxes(boxes, "odom" if k else "velodyne", stamp),
                         stamp)
    stats = ReadStats()
    frames = list(read_frames(path, stats=stats))
    assert [f.stamp_ns for f in frames] == STAMPS[:1] and stats.malformed["/points"] == 1
    assert "no transform 'odom' -> 'velodyne'" in stats.first_problem


def test_buffer_chains_interpolates_and_refuses_extrapolation():
    buffer = TransformBuffer()
    buffer.set_transform("base_link", "velodyne", MOUNT)
    for stamp in (1_000_000_000, 1_030_000_000):
        buffer.set_transform("odom", "base_link", odom_from_base(stamp), stamp)
    between = 1_012_000_000
    got = buffer.lookup("velodyne", "odom", between)
    expected = (odom_from_base(between) @ MOUNT).inverse()
    np.testing.assert_allclose(got.matrix(), expected.matrix(), atol=1e-9)
    np.testing.assert_allclose(buffer.lookup("odom", "/velodyne", between).matrix(),
                               (odom_from_base(between) @ MOUNT).matrix(), atol=1e-9)
    assert buffer.lookup("velodyne", "odom", 2_000_000_000) is None  # beyond the samples: extrapolation
    assert buffer.lookup("velodyne", "map", between) is None  # not in the tree
    np.testing.assert_allclose(buffer.lookup("velodyne", "odom", 0).matrix(),
                               (odom_from_base(1_030_000_000) @ MOUNT).inverse().matrix(), atol=1e-9)
    assert not buffer.set_transform("odom", "base_link", Transform((0.0, 0.0, np.nan), (0.0, 0.0, 0.0, 1.0)), 5)
    assert buffer.invalid == 1
    buffer.set_transform("odom", "base_link", odom_from_base(990_000_000), 990_000_000)
    buffer.forget_before(between)  # what a lookup at `between` or later needs stays
    np.testing.assert_allclose(buffer.lookup("velodyne", "odom", between).matrix(), expected.matrix(), atol=1e-9)
    assert buffer.lookup("velodyne", "odom", 995_000_000) is None  # before the kept samples now


def test_moved_detections_keep_every_hypothesis_and_turn_their_covariance():
    """The republished detections are the originals moved (not re-encoded): every hypothesis
    stays, and a pose covariance turns with the frame (x and y variances swap under 90 degrees)."""
    from pcc_ros.msg.detections import transform_detections
    from pcc_ros.msg.typestore import new_message

    boxes = Boxes([[10.0, 2.0, -0.8]], [[4.2, 1.8, 1.5]], [0.2], ["Car"], [0.9], ["a"])
    array = detection_array_from_boxes(boxes, "base_link", 1)
    detection = array.detections[0]
    second = new_message("vision_msgs/msg/ObjectHypothesisWithPose", None)
    second.hypothesis.class_id, second.hypothesis.score = "Van", 0.4
    second.pose.pose.orientation.w = 1.0
    second.pose.covariance = np.diag([1.0, 4.0, 9.0, 0.1, 0.2, 0.3]).reshape(36)
    detection.results = [*detection.results, second]
    quarter = Transform((0.0, 0.0, 0.0), tuple(quaternion_from_yaw(np.pi / 2).tolist()))
    moved = transform_detections(array.detections, quarter, "velodyne")[0]
    assert [r.hypothesis.class_id for r in moved.results] == ["Car", "Van"]
    covariance = np.asarray(moved.results[1].pose.covariance).reshape(6, 6)
    np.testing.assert_allclose(np.diag(covariance), [4.0, 1.0, 9.0, 0.2, 0.1, 0.3], atol=1e-12)
    np.testing.assert_allclose(detection.results[1].pose.covariance[:3], [1.0, 0.0, 0.0])  # the original untouched
