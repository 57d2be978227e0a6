"""tf under real rclpy, from the venv's ROS 2 wheels (no tf2_ros): the node's own /tf listener.

A ``completion_node`` (the rclpy host, backend ``mirror``) beside an independent rclpy
participant that publishes ``/tf``, ``/tf_static``, scans in ``velodyne`` and detections in a
moving, yawing ``odom`` (or in ``base_link`` behind a late static mount), and ``/clock``. Every
completed car must land in its box in the scan frame: a transform taken at the wrong stamp,
from the wrong timeline or not at all puts it elsewhere. Each test takes a few seconds.
"""

from __future__ import annotations

import threading
import time
from contextlib import contextmanager

import numpy as np
import pytest
from conftest import require_rclpy
from test_node_tf import S, assert_in_the_cars_boxes, odom_from_velodyne, pair_in_odom, scene

from pcc_ros.geometry.rotations import quaternion_from_yaw
from pcc_ros.geometry.transforms import Transform, transform_boxes

pytestmark = pytest.mark.ros
PERIOD_S = 0.1
#: base_link <- velodyne: the LiDAR 1.7 m up, turned 35 degrees.
MOUNT = Transform((0.8, 0.3, 1.7), tuple(quaternion_from_yaw(np.radians(35.0)).tolist()))


class Live:
    """A PipelineNode and an independent probe node on one executor thread; the probe publishes."""

    def __init__(self, rclpy, parameters: dict | None) -> None:
        """``parameters`` None: no node in this process (one started as a process of its own)."""
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.parameter import Parameter
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
        from rclpy.signals import SignalHandlerOptions
        from rosgraph_msgs.msg import Clock
        from sensor_msgs.msg import PointCloud2
        from tf2_msgs.msg import TFMessage
        from vision_msgs.msg import Detection3DArray

        from pcc_ros.nodes.ros_node import PipelineNode, rclpy_classes

        self.rclpy, self.classes = rclpy, rclpy_classes
        self.context = rclpy.Context()
        rclpy.init(context=self.context, signal_handler_options=SignalHandlerOptions.NO)
        self.probe = rclpy.create_node("pcc_tf_probe", context=self.context)
        static_qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                                durability=DurabilityPolicy.TRANSIENT_LOCAL)  # tf2's StaticBroadcasterQoS
        self.pub_tf = self.probe.create_publisher(TFMessage, "/tf", 100)
        self.pub_static = self.probe.create_publisher(TFMessage, "/tf_static", static_qos)
        self.pub_clock = self.probe.create_publisher(Clock, "/clock", 10)
        self.pub_points = self.probe.create_publisher(PointCloud2, "/points", qos_profile_sensor_data)
        self.pub_dets = self.probe.create_publisher(Detection3DArray, "/detections", 10)
        self.completed: list = []
        self.diagnostics: list = []
        self.probe.create_subscription(PointCloud2, "/completed", self.completed.append, 10)
        self.probe.create_subscription(DiagnosticArray, "/diagnostics", self.diagnostics.append, 10)
        self.node = None if parameters is None else PipelineNode(
            "completion_node", "completion", context=self.context,
            parameter_overrides=[Parameter(k, value=v) for k, v in {"backend": "mirror", **parameters}.items()])
        self.executor = SingleThreadedExecutor(context=self.context)
        for n in (self.node, self.probe):
            if n is not None:
                self.executor.add_node(n)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()

    @property
    def core(self):
        return self.node.core

    def wait_for(self, predicate, timeout: float = 10.0) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if predicate():
                return True
            time.sleep(0.02)
        return predicate()

    def connected(self, timeout: float = 10.0) -> None:
        """Both directions matched (the node's readers and the probe's), then a moment for discovery."""
        pubs = (self.pub_tf, self.pub_static, self.pub_points, self.pub_dets)
        assert self.wait_for(lambda: all(p.get_subscription_count() >= 1 for p in pubs)
                             and self.probe.count_publishers("/completed") == 1, timeout), "the node did not match"
        time.sleep(0.5)

    def tf(self, parent: str, child: str, pose: Transform, stamp_ns: int, static: bool = False) -> None:
        from pcc_ros.data.bag_writer import tf_message

        msg = tf_message([(parent, child, pose.matrix())], stamp_ns)
        rclpy_msg = _to_rclpy(msg, self.classes)
        (self.pub_static if static else self.pub_tf).publish(rclpy_msg)

    def clock(self, stamp_ns: int) -> None:
        from rosgraph_msgs.msg import Clock

        msg = Clock()
        msg.clock.sec, msg.clock.nanosec = divmod(int(stamp_ns), S)
        self.pub_clock.publish(msg)

    def frame(self, cloud, dets) -> None:
        self.pub_points.publish(cloud)
        self.pub_dets.publish(dets)

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=2)
        for n in (self.probe, self.node):
            if n is not None:
                n.destroy_node()
        self.rclpy.try_shutdown(context=self.context)


def _to_rclpy(msg, classes):
    """A rosbags TFMessage as rclpy's (field by field)."""
    out = classes("tf2_msgs/msg/TFMessage")()
    for stamped in msg.transforms:
        t = classes("geometry_msgs/msg/TransformStamped")()
        t.header.frame_id, t.child_frame_id = stamped.header.frame_id, stamped.child_frame_id
        t.header.stamp.sec, t.header.stamp.nanosec = stamped.header.stamp.sec, stamped.header.stamp.nanosec
        for part in ("translation", "rotation"):
            src, dst = getattr(stamped.transform, part), getattr(t.transform, part)
            for axis in ("x", "y", "z", "w") if part == "rotation" else ("x", "y", "z"):
                setattr(dst, axis, float(getattr(src, axis)))
        out.transforms.append(t)
    return out


def diagnostic_values(g: Live) -> dict[str, str]:
    """The node's latest /diagnostics key/values."""
    return {kv.key: kv.value for kv in g.diagnostics[-1].status[0].values} if g.diagnostics else {}


@contextmanager
def live(parameters: dict | None):
    rclpy = require_rclpy()
    graph = Live(rclpy, parameters)
    try:
        yield graph
    finally:
        graph.close()


def _stamp(msg) -> int:
    return msg.header.stamp.sec * S + msg.header.stamp.nanosec


def test_a_node_started_from_the_venv_completes_cars_detected_in_a_moving_yawing_odom_frame(tmp_path):
    """The node as a process of the venv's interpreter (the wheels: no tf2_ros), an independent
    participant publishing /tf odom <- base_link (driving, turning; 50 Hz, lagging the scans by up to
    half a second) and a /tf_static mount latched before the node started: every frame waits for its
    transform, then is answered with every car in its box; none dropped."""
    import os
    import signal
    import subprocess
    import sys

    with live(None) as g:
        g.tf("base_link", "velodyne", MOUNT, 0, static=True)  # latched before the node exists
        log = (tmp_path / "node.log").open("w")
        node = subprocess.Popen(
            [sys.executable, "-m", "pcc_ros.nodes.completion_node", "--ros-args", "-p", "backend:=mirror",
             "-p", "tf_timeout:=3.0"], env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)},
            stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        try:
            g.connected(timeout=120)
            t0, n = 1000 * S, 5
            for k in range(n):  # half a second of scans before localisation catches up: the frames wait
                stamp = t0 + k * S // 10
                g.frame(*pair_in_odom(stamp, odom_from_base(stamp) @ MOUNT, g.classes))  # odom <- velodyne
                time.sleep(PERIOD_S)
            for j in range(-2, 5 * n + 2):  # then /tf at 50 Hz over the scans
                tf_stamp = t0 + j * S // 50
                g.tf("odom", "base_link", odom_from_base(tf_stamp), tf_stamp)
            assert g.wait_for(lambda: len(g.completed) == n
                              and diagnostic_values(g).get("frames") == str(n), 30), diagnostic_values(g)
        finally:
            node.send_signal(signal.SIGINT)
            node.wait(timeout=30)
            log.close()
    text = (tmp_path / "node.log").read_text()
    assert node.returncode == 0 and "Traceback" not in text, text
    assert sorted(_stamp(m) for m in g.completed) == [t0 + k * S // 10 for k in range(n)]
    for msg in g.completed:
        assert msg.header.frame_id == "velodyne"
        assert_in_the_cars_boxes(msg)
    values = diagnostic_values(g)
    assert values["frames_without_transform"] == "0" and values["frames_released_after_waiting"] == str(n), values


def odom_from_base(stamp_ns: int) -> Transform:
    t = stamp_ns * 1e-9
    return Transform((2.0 + 8.0 * t, -1.0 + 1.5 * t, 0.0), tuple(quaternion_from_yaw(0.4 + 0.3 * t).tolist()))


def test_a_tf_publisher_that_stalls_and_resumes():
    """tf stops for 0.8 s: frames wait tf_timeout (0.3 s), the oldest are dropped and counted (WARN on
    /diagnostics with the reason), none is processed in a wrong frame; when tf resumes the waiting
    frames and every later one are answered in the right place."""
    with live({"tf_timeout": 0.3}) as g:
        g.connected()
        t0, n, stall = 2000 * S, 16, range(4, 12)
        for k in range(n):
            stamp = t0 + k * S // 10
            g.frame(*pair_in_odom(stamp, odom_from_velodyne(stamp), g.classes))
            if k not in stall:
                for j in (-2, -1, 0, 1, 2):  # samples around the scan (when tf runs, it runs ahead)
                    g.tf("odom", "velodyne", odom_from_velodyne(stamp + j * S // 20), stamp + j * S // 20)
            time.sleep(PERIOD_S)
        core = g.core
        assert g.wait_for(lambda: len(g.completed) + core.no_transform + core.pairer.stats.dropped_pairs == n
                          and not len(core.tf_wait)), core.diagnostics_values()
        level, message = _status(core)
    answered = sorted((_stamp(m) - t0) * 10 // S for m in g.completed)
    assert {0, 1, 2, 3, 12, 13, 14, 15} <= set(answered), answered
    assert 1 <= core.no_transform <= len(stall), core.diagnostics_values()
    for msg in g.completed:
        assert_in_the_cars_boxes(msg)
    assert level == 1 and "dropped: no transform 'odom' -> 'velodyne' within tf_timeout" in message, message


def test_a_static_transform_published_after_the_first_scans_is_picked_up():
    with live({"tf_timeout": 0.2}) as g:
        g.connected()
        t0, n = 3000 * S, 8
        points, boxes = scene()
        from pcc_ros.msg.detections import detection_array_from_boxes
        from pcc_ros.msg.pointcloud2 import create_cloud

        in_base = transform_boxes(boxes, MOUNT.matrix())
        for k in range(n):
            stamp = t0 + k * S // 10
            if k == 4:
                g.tf("base_link", "velodyne", MOUNT, stamp, static=True)  # the mount, latched late
            g.frame(create_cloud(points, ["x", "y", "z"], "velodyne", stamp, g.classes),
                    detection_array_from_boxes(in_base, "base_link", stamp, g.classes))
            time.sleep(PERIOD_S * 3)  # each frame's tf_timeout runs out before the next
        assert g.wait_for(lambda: len(g.completed) + g.core.no_transform == n)
    answered = sorted((_stamp(m) - t0) * 10 // S for m in g.completed)
    # frames 0-2 waited their 0.2 s in vain (frame 3 too, unless the worker came back to it only after the
    # mount arrived); 4-7 found it
    assert {4, 5, 6, 7} <= set(answered) <= {3, 4, 5, 6, 7} and len(answered) + g.core.no_transform == n
    for msg in g.completed:
        assert_in_the_cars_boxes(msg)


def test_a_looped_bag_under_sim_time_resets_and_serves_the_new_timeline():
    """use_sim_time with /clock: the second loop goes back to the same stamps with the vehicle
    elsewhere and tf sampled at other instants; the old samples would put its cars in the wrong
    place (interpolated against the first loop's poses). The jump resets pairing, queues and tf."""
    with live({"tf_timeout": 1.0, "use_sim_time": True}) as g:
        g.connected()
        t0, n = 100 * S, 4
        answered_before = 0
        for loop, (yaw0, phase) in enumerate(((0.4, 0), (2.0, S // 100))):
            g.clock(t0 - S // 10)
            time.sleep(0.2)  # /clock first, as a player publishes it
            for k in range(n):
                stamp = t0 + k * S // 10
                g.clock(stamp)
                for j in range(-3, 4):
                    tf_stamp = stamp + j * S // 50 + phase
                    g.tf("odom", "velodyne", odom_from_velodyne(tf_stamp, yaw0), tf_stamp)
                time.sleep(0.02)
                g.frame(*pair_in_odom(stamp, odom_from_velodyne(stamp, yaw0), g.classes))
                time.sleep(PERIOD_S)
            expected = answered_before + n
            assert g.wait_for(lambda e=expected: len(g.completed) == e), (loop, g.core.diagnostics_values())
            answered_before = len(g.completed)
            if loop == 0:
                assert g.core.time_jumps == 0
        assert g.core.time_jumps == 1, g.core.diagnostics_values()
        level, message = _status(g.core)
    for msg in g.completed:
        assert_in_the_cars_boxes(msg)
    assert level == 1 and "clock jumped back 1 time(s)" in message


def _status(core) -> tuple[int, str]:
    status = core.diagnostics_message().status[0]
    return ord(status.level) if isinstance(status.level, bytes) else int(status.level), status.message


def test_a_bag_looped_by_pcc_play_with_clock_is_served_loop_after_loop(tmp_path):
    """``pcc play BAG --loop --clock`` (an independent process) replays a bag with ``/tf``,
    ``/tf_static`` and detections in ``odom`` to a node under ``use_sim_time``: each new loop moves
    ``/clock`` back; the node resets and answers every loop, every car in its box."""
    import os
    import signal
    import subprocess
    import sys

    from test_replay_tf import STAMPS, messages
    from test_replay_tf import scene as replay_scene

    from pcc_ros.data.bag_writer import atomic_bag
    from pcc_ros.geometry.boxes import points_in_boxes
    from pcc_ros.msg.pointcloud2 import read_xyz

    bag = tmp_path / "loop"
    with atomic_bag(bag) as writer:
        for time_ns, topic, msgtype, msg in messages():
            writer.write(topic, msgtype, msg, time_ns)
    with live({"tf_timeout": 1.0, "use_sim_time": True}) as g:
        play = subprocess.Popen(
            [sys.executable, "-m", "pcc_ros.cli", "play", str(bag), "--loop", "--clock", "--wait-subscribers", "1",
             "--wait-topics", "/points", "/detections", "/tf", "--delay", "1"],
            env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}, stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT, text=True, start_new_session=True)
        try:
            assert g.wait_for(lambda: g.core.time_jumps >= 2 and len(g.completed) >= 3 * len(STAMPS), 60), (
                g.core.diagnostics_values())
        finally:
            play.send_signal(signal.SIGINT)
            out = play.communicate(timeout=30)[0]
        values = g.core.diagnostics_values()
    assert play.returncode == 0, out
    assert int(values["frames_without_transform"]) == 0, values
    boxes_of = {stamp: replay_scene(k)[1] for k, stamp in enumerate(STAMPS)}
    for msg in g.completed:
        cloud = read_xyz(msg, ["instance"])
        boxes = boxes_of[_stamp(msg)]
        for i in np.unique(cloud[:, 3].astype(int)):
            pts = cloud[cloud[:, 3] == i, :3]
            assert len(points_in_boxes(pts, boxes[np.array([i])], margin=0.2)[0]) >= 0.95 * len(pts)
