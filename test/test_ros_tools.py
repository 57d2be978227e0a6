"""``pcc play`` -> the nodes -> this test's subscriber, all real rclpy processes; ``pcc echo``.

A 4-frame SynthCars bag generated at test time (conftest's ``synth_bag``: every clone has it)
and, where ../shared/data is laid, a 3-frame real-KITTI bag are played by ``pcc play``
(rclpy, the recorded CDR bytes as they are); ``completion_node`` and ``detection_filter_node``
run as processes with the ``mirror`` backend; what arrives must be byte-identical to what
``pcc replay`` records for the same bag (offline == online). A malformed PointCloud2 on the
wire is logged and skipped and the node keeps serving. Every process is stopped (SIGINT, then SIGKILL) in a ``finally``.
"""

from __future__ import annotations

import copy
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import assert_named_failure, require_rclpy, run_cli

from pcc_ros.cli.main import main as pcc
from pcc_ros.data.bag import open_bag as open_reader
from pcc_ros.msg.stamps import ns_to_stamp, stamp_to_ns
from pcc_ros.msg.typestore import get_typestore

pytestmark = [pytest.mark.ros, pytest.mark.slow]

PCC = [sys.executable, "-m", "pcc_ros.cli"]
OUTPUTS = {"completed": "sensor_msgs/msg/PointCloud2", "detections_filtered": "vision_msgs/msg/Detection3DArray"}


def _read_topic(bag: Path, topic: str) -> dict[int, object]:
    from rosbags.highlevel import AnyReader

    with AnyReader([bag], default_typestore=get_typestore()) as reader:
        conns = [c for c in reader.connections if c.topic == topic]
        return {
            stamp_to_ns(m.header.stamp): m
            for m in (reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages(connections=conns))
        }


def _wait(predicate, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.05)
    return predicate()


def _stamp_of(raw: bytes, msgtype: str) -> int:
    return stamp_to_ns(get_typestore().deserialize_cdr(raw, msgtype).header.stamp)


@pytest.fixture(scope="module")
def kitti_bag3(tmp_path_factory, shared_data) -> Path:
    """The first 3 frames of KITTI tracking 0000 with their PointRCNN detections, as a bag."""
    bag = tmp_path_factory.mktemp("ros_tools_kitti") / "kitti3"
    kitti = shared_data / "kitti_tracking"
    assert pcc(["convert", "kitti-tracking", str(kitti), "--sequence", "0000", "--first", "0", "--frames", "3",
                "--detections", str(kitti / "detections" / "pointrcnn"), "--out", str(bag)]) == 0
    return bag


#: The parameters of the nodes and of the replays they are compared with: the mirror backend, and
#: a fixed beam model (``sensor: auto`` estimates it from the scans a node has seen, so nodes that
#: saw the generated scans first would judge the KITTI ones with that estimate, a fresh replay not).
PARAMS = "/**:\n  ros__parameters:\n    backend: mirror\n    sensor: hdl64\n"


def _replay_references(bag: Path, tmp: Path, params: Path) -> dict[str, dict[int, object]]:
    """What ``pcc replay`` records for ``bag`` with the nodes' parameters: the online outputs' reference."""
    assert pcc(["replay", str(bag), "--out", str(tmp / "ref_c"), "--config", str(params), "--no-copy-inputs"]) == 0
    assert pcc(["replay", str(bag), "--out", str(tmp / "ref_f"), "--config", str(params), "--filter",
                "--no-copy-inputs"]) == 0
    return {"completed": _read_topic(tmp / "ref_c", "/completed"),
            "detections_filtered": _read_topic(tmp / "ref_f", "/detections_filtered")}


@pytest.fixture(scope="module")
def graph(tmp_path_factory, synth_bag):
    """The two node processes and an rclpy probe (raw subscriptions); the generated bag."""
    rclpy = require_rclpy()
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rclpy.signals import SignalHandlerOptions

    from pcc_ros.nodes.ros_node import rclpy_classes

    tmp = tmp_path_factory.mktemp("ros_tools")
    params = tmp / "params.yaml"
    params.write_text(PARAMS)

    procs: dict[str, subprocess.Popen] = {}
    logs = {}
    context = rclpy.Context()
    rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
    probe = rclpy.create_node("pcc_tools_probe", context=context)
    executor = SingleThreadedExecutor(context=context)
    try:
        for module in ("completion_node", "detection_filter_node"):
            logs[module] = tmp / f"{module}.log"
            with logs[module].open("w") as log:
                procs[module] = subprocess.Popen(
                    [sys.executable, "-m", f"pcc_ros.nodes.{module}", "--ros-args", "--params-file", str(params)],
                    stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, start_new_session=True,
                )
        got: dict[str, list[bytes]] = {name: [] for name in OUTPUTS}
        lock = threading.Lock()

        def recorder(name):
            def record(raw: bytes) -> None:
                with lock:
                    got[name].append(raw)

            return record

        reliable = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
        for name, msgtype in OUTPUTS.items():
            probe.create_subscription(rclpy_classes(msgtype), f"/{name}", recorder(name), reliable, raw=True)
        executor.add_node(probe)
        threading.Thread(target=executor.spin, daemon=True).start()
        ready = _wait(lambda: all(probe.count_publishers(f"/{n}") == 1 for n in OUTPUTS)
                      and probe.count_subscribers("/points") == 2, 180)
        assert ready, {n: p.read_text()[-2000:] for n, p in logs.items()}
        yield {"bag": synth_bag, "params": params, "probe": probe, "got": got, "lock": lock, "logs": logs,
               "procs": procs}
    finally:
        for proc in procs.values():
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGINT)
        for proc in procs.values():
            try:
                proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait(timeout=5)
        executor.shutdown(timeout_sec=2)
        probe.destroy_node()
        rclpy.try_shutdown(context=context)
    for name, proc in procs.items():
        assert proc.returncode == 0, (name, logs[name].read_text()[-2000:])


@pytest.mark.parametrize("source", ["synth", "kitti"])
def test_play_through_the_nodes_matches_replay(graph, source, request, tmp_path):
    """Generated frames in every clone; the real KITTI frames where ../shared/data is laid."""
    bag = graph["bag"] if source == "synth" else request.getfixturevalue("kitti_bag3")
    n = len(_read_topic(bag, "/points"))
    reference = _replay_references(bag, tmp_path, graph["params"])
    got = graph["got"]
    with graph["lock"]:
        for values in got.values():
            values.clear()
    play = subprocess.run(
        [*PCC, "play", str(bag), "--rate", "0.5", "--wait-subscribers", "2",
         "--wait-topics", "/points", "/detections", "--wait-timeout", "60", "--delay", "1.0"],
        capture_output=True, text=True, timeout=180,
    )
    assert play.returncode == 0, play.stderr
    assert f"/points: {n} messages" in play.stdout and f"/detections: {n} messages" in play.stdout
    assert {k: len(v) for k, v in reference.items()} == {"completed": n, "detections_filtered": n}
    arrived = _wait(lambda: all(len(got[k]) >= n for k in OUTPUTS), 60)
    assert arrived, {k: len(v) for k, v in got.items()}
    store = get_typestore()
    for name, msgtype in OUTPUTS.items():
        received = {_stamp_of(raw, msgtype): raw for raw in got[name]}
        assert received.keys() == reference[name].keys()
        for stamp, raw in received.items():  # offline == online, every field to the bit
            ref = bytes(store.serialize_cdr(reference[name][stamp], msgtype))
            # Compared as canonical CDR (decoded, encoded again by rosbags): the bytes on the wire may
            # carry whatever the sender's alignment padding held (seen after a string: b"cc_" for
            # zeros) and Fast DDS's trailing padding; every value, float bits included, must match.
            again = bytes(store.serialize_cdr(store.deserialize_cdr(raw, msgtype), msgtype))
            assert again == ref, (name, stamp)
    assert min(len(r) for r in got["completed"]) > 1000  # real completions, not empty clouds


def _probe_publishers(graph):
    """The bag's first frame (cloud, detections, stamp) and the probe's publishers of the nodes' inputs."""
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import PointCloud2
    from vision_msgs.msg import Detection3DArray

    clouds = _read_topic(graph["bag"], "/points")
    dets = _read_topic(graph["bag"], "/detections")
    stamp0 = min(clouds)
    pub_cloud = graph["probe"].create_publisher(PointCloud2, "/points", qos_profile_sensor_data)
    pub_dets = graph["probe"].create_publisher(Detection3DArray, "/detections", 10)
    return clouds[stamp0], dets[stamp0], pub_cloud, pub_dets


def test_malformed_cloud_on_the_wire_is_logged_skipped_and_the_node_keeps_serving(graph):
    got, lock = graph["got"], graph["lock"]
    store = get_typestore()
    cloud0, det0, pub_cloud, pub_dets = _probe_publishers(graph)
    assert _wait(lambda: pub_cloud.get_subscription_count() == 2 and pub_dets.get_subscription_count() == 2, 30)

    def send(stamp_ns: int, truncate: bool = False) -> None:
        cloud, det = copy.deepcopy(cloud0), copy.deepcopy(det0)
        cloud.header.stamp = det.header.stamp = ns_to_stamp(stamp_ns)
        if truncate:
            cloud.data = np.asarray(cloud.data)[:1000]  # width / row_step claim thousands of points, data 62
        pub_cloud.publish(bytes(store.serialize_cdr(cloud, "sensor_msgs/msg/PointCloud2")))
        pub_dets.publish(bytes(store.serialize_cdr(det, "vision_msgs/msg/Detection3DArray")))

    def completed(stamp_ns: int) -> bool:
        with lock:
            return any(_stamp_of(raw, OUTPUTS["completed"]) == stamp_ns for raw in got["completed"])

    # Handshake: a new best-effort writer's first samples can precede the readers' side of
    # discovery; once one frame made the round trip the path is established both ways.
    warm, bad, good = (s * 10**9 for s in (1_999_999_999, 2_000_000_000, 2_000_000_001))
    assert any(send(warm + k * 10**6) or _wait(lambda k=k: completed(warm + k * 10**6), 2.0) for k in range(20))
    send(bad, truncate=True)
    log = graph["logs"]["completion_node"]
    assert _wait(lambda: "skipped a frame" in log.read_text(), 20)
    send(good)
    assert _wait(lambda: completed(good), 30)
    assert not completed(bad)
    assert all(p.poll() is None for p in graph["procs"].values())  # both nodes still running
    assert "PointCloud2" in log.read_text() and "Traceback" not in log.read_text()


def test_echo_finds_the_type_on_the_graph_and_prints_filtered_detections(graph):
    store = get_typestore()
    cloud0, det0, pub_cloud, pub_dets = _probe_publishers(graph)
    echo = subprocess.Popen(
        [*PCC, "echo", "/detections_filtered", "--count", "1", "--timeout", "60"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
    )
    try:
        k = 0
        while echo.poll() is None and k < 120:  # volatile topics: keep sending until echo has matched
            cloud0.header.stamp = det0.header.stamp = ns_to_stamp((2_100_000_000 + k) * 10**9)
            pub_cloud.publish(bytes(store.serialize_cdr(cloud0, "sensor_msgs/msg/PointCloud2")))
            pub_dets.publish(bytes(store.serialize_cdr(det0, "vision_msgs/msg/Detection3DArray")))
            k += 1
            time.sleep(0.5)
        out, err = echo.communicate(timeout=30)
    finally:
        if echo.poll() is None:
            os.killpg(echo.pid, signal.SIGKILL)
            echo.wait(timeout=5)
    assert echo.returncode == 0, err
    assert "Detection3DArray" in out and "velodyne" in out and "id=" in out


def test_play_and_echo_without_rclpy_say_how_to_get_it(monkeypatch, tmp_path, caplog):
    monkeypatch.setitem(sys.modules, "rclpy", None)  # `import rclpy` raises ImportError
    for argv in (["play", str(tmp_path / "bag")], ["echo", "/completed"]):
        assert_named_failure(*run_cli(argv, caplog), "needs rclpy", "make setup")


def test_play_names_a_damaged_bag_and_skips_undecodable_messages(graph, tmp_path):
    """A truncated bag is one named error line (rc 1, no traceback); a message whose CDR
    cannot be decoded is skipped, counted and never put on the graph."""
    from rosbags.rosbag2 import Writer
    from rosbags.rosbag2.enums import StoragePlugin

    require_rclpy()
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    truncated = tmp_path / "truncated"
    mcap = next(Path(graph["bag"]).glob("*.mcap"))
    truncated.mkdir()
    (truncated / mcap.name).write_bytes(mcap.read_bytes()[: mcap.stat().st_size // 2])
    (truncated / "metadata.yaml").write_bytes((Path(graph["bag"]) / "metadata.yaml").read_bytes())
    run = subprocess.run([*PCC, "play", str(truncated)], capture_output=True, text=True, timeout=120, env=env)
    assert_named_failure(run.returncode, run.stderr, truncated)

    store = get_typestore()
    bad = tmp_path / "bad_cdr"
    writer = Writer(bad, version=9, storage_plugin=StoragePlugin.MCAP)
    writer.open()
    with open_reader(graph["bag"]) as reader:
        conns = [c for c in reader.connections if c.topic == "/points"]
        conn = writer.add_connection("/points", conns[0].msgtype, typestore=store)
        for i, (_, t, raw) in enumerate(reader.messages(connections=conns)):
            writer.write(conn, t, bytes(raw)[:100] if i == 1 else bytes(raw))
    writer.close()
    run = subprocess.run([*PCC, "play", str(bad), "--rate", "20"], capture_output=True, text=True, timeout=120, env=env)
    assert run.returncode == 0, run.stderr
    n = len(_read_topic(graph["bag"], "/points"))
    assert f"/points: {n - 1} messages (1 undecodable, not played)" in run.stdout, run.stdout
    assert "undecodable" in run.stderr and "Traceback" not in run.stderr
