"""The managed (lifecycle) nodes under real rclpy, driven from another process.

Each managed node runs as its own process (the ``*_managed`` entry functions); this test process
is the independent party: a client node calls ``/<node>/change_state`` and ``/<node>/get_state``
(lifecycle_msgs services), publishes scans and detections and records the node's output, so what
is checked is what a lifecycle manager on the graph sees: nothing subscribed or published before
``activate`` and after ``deactivate``, frames answered while active, a configure that fails with
its reason and leaves the node unconfigured.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import require_rclpy

pytestmark = pytest.mark.ros

REPO = Path(__file__).resolve().parents[1]
#: lifecycle_msgs/msg/State ids
UNCONFIGURED, INACTIVE, ACTIVE, FINALIZED = 1, 2, 3, 4


def start_managed(node: str, params: dict[str, str]) -> subprocess.Popen:
    """``<node>_managed`` as a process of its own (its own session: SIGINT reaches only it)."""
    module = {"completion_node": "completion_node", "detection_filter_node": "detection_filter_node"}[node]
    code = f"import sys; from pcc_ros.nodes.{module} import main_managed; sys.exit(main_managed())"
    args = [a for k, v in params.items() for a in ("-p", f"{k}:={v}")]
    env = {**os.environ, "PYTHONPATH": str(REPO), "PYTHONUNBUFFERED": "1", "RCUTILS_LOGGING_BUFFERED_STREAM": "0"}
    return subprocess.Popen([sys.executable, "-c", code, "--ros-args", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, env=env, start_new_session=True)


def stop(proc: subprocess.Popen) -> str:
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
    try:
        out, _ = proc.communicate(timeout=20)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate()
    return out


class Manager:
    """The independent client: lifecycle services, a player and a recorder of one output."""

    def __init__(self, rclpy, node: str, output: str, output_type: type) -> None:
        from lifecycle_msgs.srv import ChangeState, GetState
        from sensor_msgs.msg import PointCloud2
        from vision_msgs.msg import Detection3DArray

        self.rclpy, self.node_name = rclpy, node
        self.client = rclpy.create_node("lifecycle_manager_probe")
        self.change = self.client.create_client(ChangeState, f"/{node}/change_state")
        self.get = self.client.create_client(GetState, f"/{node}/get_state")
        self.got: list = []
        self.client.create_subscription(output_type, output, self.got.append, 10)
        self.pub_cloud = self.client.create_publisher(PointCloud2, "/points", 10)
        self.pub_det = self.client.create_publisher(Detection3DArray, "/detections", 10)
        self.output = output

    def call(self, client, request, timeout: float = 120.0):
        assert client.wait_for_service(timeout_sec=60.0), f"{client.srv_name} never appeared"
        future = client.call_async(request)
        self.rclpy.spin_until_future_complete(self.client, future, timeout_sec=timeout)
        assert future.done(), f"{client.srv_name}: no answer in {timeout} s"
        return future.result()

    def state(self) -> int:
        from lifecycle_msgs.srv import GetState

        return self.call(self.get, GetState.Request()).current_state.id

    def transition(self, label: str) -> bool:
        from lifecycle_msgs.msg import Transition
        from lifecycle_msgs.srv import ChangeState

        ids = {"configure": Transition.TRANSITION_CONFIGURE, "activate": Transition.TRANSITION_ACTIVATE,
               "deactivate": Transition.TRANSITION_DEACTIVATE, "cleanup": Transition.TRANSITION_CLEANUP,
               "shutdown": Transition.TRANSITION_UNCONFIGURED_SHUTDOWN}
        return self.call(self.change, ChangeState.Request(transition=Transition(id=ids[label]))).success

    def play(self, cloud, detections, seconds: float, until_answered: bool = False) -> int:
        """Publish the pair every 0.2 s for ``seconds`` (or until an output arrives); returns the
        outputs received meanwhile."""
        before = len(self.got)
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline and not (until_answered and len(self.got) > before):
            self.pub_cloud.publish(cloud)
            self.pub_det.publish(detections)
            tick = time.monotonic() + 0.2
            while time.monotonic() < tick:
                self.rclpy.spin_once(self.client, timeout_sec=0.05)
        return len(self.got) - before

    def subscribers(self, topic: str) -> int:
        return self.client.count_subscribers(topic)

    def publishers(self, topic: str) -> int:
        return self.client.count_publishers(topic)


def frame():
    from pcc_ros.msg.detections import detection_array_from_boxes
    from pcc_ros.msg.pointcloud2 import create_cloud
    from pcc_ros.nodes.ros_node import rclpy_classes
    from pcc_ros.types import Boxes

    rng = np.random.default_rng(0)
    pts = (rng.normal(size=(500, 3)) * [1.5, 0.7, 0.5] + [10, 0, -0.8]).astype(np.float32)
    boxes = Boxes([[10, 0, -0.8]], [[4, 1.7, 1.5]], [0.0], ["Car"], [0.9], ["1"])
    stamp = 1_000_000_000
    return (create_cloud(pts, ["x", "y", "z"], "velodyne", stamp, rclpy_classes),
            detection_array_from_boxes(boxes, "velodyne", stamp, rclpy_classes))


@pytest.mark.parametrize(("node", "params", "output", "type_name"), [
    ("completion_node", {"backend": "mirror"}, "/completed", "sensor_msgs.msg.PointCloud2"),
    ("detection_filter_node", {"backend": "mirror"}, "/detections_filtered", "vision_msgs.msg.Detection3DArray"),
])
def test_managed_node_serves_only_while_active(isolated_ros_graph, node, params, output, type_name):
    rclpy = require_rclpy()
    import importlib

    module, _, cls = type_name.rpartition(".")
    output_type = getattr(importlib.import_module(module), cls)
    cloud, detections = frame()
    proc = start_managed(node, params)
    rclpy.init()
    manager = None
    try:
        manager = Manager(rclpy, node, output, output_type)
        assert manager.state() == UNCONFIGURED
        assert manager.transition("configure")
        assert manager.state() == INACTIVE
        # configured, not active: no subscription to the inputs, nothing published
        assert manager.subscribers("/points") == 0 and manager.subscribers("/detections") == 0
        assert manager.play(cloud, detections, 1.5) == 0
        assert manager.transition("activate") and manager.state() == ACTIVE
        assert manager.play(cloud, detections, 30.0, until_answered=True) >= 1
        assert manager.got[-1].header.frame_id == "velodyne"
        assert manager.transition("deactivate") and manager.state() == INACTIVE
        time.sleep(0.5)
        assert manager.play(cloud, detections, 2.0) == 0
        assert manager.subscribers("/points") == 0 and manager.publishers(output) == 0
        assert manager.transition("activate") and manager.state() == ACTIVE  # no reload: serves again at once
        assert manager.play(cloud, detections, 30.0, until_answered=True) >= 1
        assert manager.transition("deactivate") and manager.transition("cleanup")
        assert manager.state() == UNCONFIGURED
        assert manager.transition("shutdown") and manager.state() == FINALIZED
    finally:
        if manager is not None:
            manager.client.destroy_node()
        rclpy.try_shutdown()
        log = stop(proc)
    assert proc.returncode == 0, log
    assert "Traceback" not in log, log
    assert "configured: pipeline loaded" in log and "deactivated: not serving" in log, log


@pytest.mark.parametrize(("params", "reason"), [
    ({"backend": "nope"}, "unknown completion backend 'nope'"),
    ({"backend": "mirror", "qos_overrides./point.subscription.depth": "3"}, "qos_overrides./point.subscription"),
    ({"backend": "mirror", "min_points": "0"}, "min_points"),
])
def test_an_unconfigurable_parameter_fails_configure_with_its_reason(isolated_ros_graph, params, reason):
    rclpy = require_rclpy()
    from sensor_msgs.msg import PointCloud2

    proc = start_managed("completion_node", params)
    rclpy.init()
    manager = None
    try:
        manager = Manager(rclpy, "completion_node", "/completed", PointCloud2)
        assert not manager.transition("configure")
        assert manager.state() == UNCONFIGURED
        assert manager.subscribers("/points") == 0
    finally:
        if manager is not None:
            manager.client.destroy_node()
        rclpy.try_shutdown()
        log = stop(proc)
    assert proc.returncode == 0, log
    failed = [line for line in log.splitlines() if "configure failed" in line]
    assert failed and reason in failed[0] and "ERROR" in failed[0], log
    assert "Traceback" not in log, log
