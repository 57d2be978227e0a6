"""End to end across processes over loopback: ``pcc play`` -> DDS nodes -> this test's subscriber.

A 3-frame real-KITTI bag is played onto a private DDS domain (unique ROS_DOMAIN_ID,
localhost discovery); ``pcc node completion`` and ``pcc node filter`` run on the DDS
runtime with the ``mirror`` backend; what arrives must be byte-identical to what
``pcc replay`` records for the same bag. A malformed PointCloud2 sent on the wire is
logged and skipped and the node keeps serving. Every process runs under a timeout and is
killed in a ``finally``.
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

pytest.importorskip("cyclonedds")

from pcc_ros.cli import main as pcc
from pcc_ros.msg.stamps import stamp_to_ns
from pcc_ros.msg.typestore import get_typestore
from pcc_ros.runtime.base import RELIABLE, SENSOR_DATA
from pcc_ros.runtime.discovery import Discovery

pytestmark = pytest.mark.slow

CLOUD = "sensor_msgs/msg/PointCloud2"
DETS = "vision_msgs/msg/Detection3DArray"
PCC = [sys.executable, "-m", "pcc_ros.cli"]


def _serialize(msg, msgtype):
    return bytes(get_typestore().serialize_cdr(msg, msgtype))


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


@pytest.fixture(scope="module")
def graph(tmp_path_factory, shared_data):
    """The bag, replay references, two node processes and an in-process probe on a private domain."""
    from pcc_ros.runtime.dds import DdsRuntime

    tmp = tmp_path_factory.mktemp("dds_e2e")
    bag = tmp / "kitti3"
    assert pcc([
        "convert", "kitti-tracking", str(shared_data / "kitti_tracking"), "--sequence", "0000", "--first", "0",
        "--frames", "3", "--detections", str(shared_data / "kitti_tracking" / "detections" / "pointrcnn"),
        "--out", str(bag),
    ]) == 0
    assert pcc(["replay", str(bag), "--out", str(tmp / "ref_c"), "--backend", "mirror", "--no-copy-inputs"]) == 0
    assert pcc(["replay", str(bag), "--out", str(tmp / "ref_f"), "--backend", "mirror", "--filter",
                "--no-copy-inputs"]) == 0
    reference = {"completed": _read_topic(tmp / "ref_c", "/completed"),
                 "detections_filtered": _read_topic(tmp / "ref_f", "/detections_filtered")}

    domain = 150 + os.getpid() % 80
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain), "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
    env.pop("CYCLONEDDS_URI", None)
    procs: list[subprocess.Popen] = []
    logs = {}
    probe = None
    try:
        for mode in ("completion", "filter"):
            logs[mode] = tmp / f"{mode}.log"
            procs.append(subprocess.Popen(
                ["timeout", "240", *PCC, "node", mode, "--transport", "dds", "--backend", "mirror"],
                env=env, stdout=subprocess.DEVNULL, stderr=open(logs[mode], "w"), start_new_session=True,
            ))
        probe = DdsRuntime("probe", discovery=Discovery.from_env(env))
        got: dict[str, list] = {"completed": [], "detections_filtered": []}
        subs = {name: probe.create_subscription(f"/{name}", t, got[name].append, RELIABLE)
                for name, t in (("completed", CLOUD), ("detections_filtered", DETS))}
        probe.start()
        ready = _wait(lambda: all(s.matched() >= 1 for s in subs.values()), 90)
        assert ready, f"nodes did not come up: {[p.read_text() for p in logs.values()]}"
        yield {"bag": bag, "env": env, "probe": probe, "got": got, "reference": reference, "logs": logs,
               "procs": procs}
    finally:
        if probe is not None:
            probe.shutdown()
        for proc in procs:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGINT)
        for proc in procs:
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait(timeout=5)


def test_play_through_dds_nodes_matches_replay(graph):
    got, reference = graph["got"], graph["reference"]
    play = subprocess.run(
        [*PCC, "play", str(graph["bag"]), "--rate", "0.25", "--wait-subscribers", "2",
         "--wait-topics", "/points", "/detections", "--wait-timeout", "60"],
        env=graph["env"], capture_output=True, text=True, timeout=120,
    )
    assert play.returncode == 0, play.stderr
    assert "/points: 3 messages" in play.stdout
    expected = {k: len(v) for k, v in reference.items()}
    assert expected == {"completed": 3, "detections_filtered": 3}
    arrived = _wait(lambda: all(len(got[k]) >= n for k, n in expected.items()), 60)
    assert arrived, {k: len(v) for k, v in got.items()}
    for name, msgtype in (("completed", CLOUD), ("detections_filtered", DETS)):
        received = {stamp_to_ns(m.header.stamp): m for m in got[name]}
        assert received.keys() == reference[name].keys()
        for stamp, msg in received.items():
            assert _serialize(msg, msgtype) == _serialize(reference[name][stamp], msgtype), (name, stamp)
    assert min(len(m.data) for m in got["completed"]) > 1000  # real completions, not empty clouds
    assert all(len(m.detections) > 0 for m in got["detections_filtered"])


def test_malformed_cloud_on_the_wire_is_logged_skipped_and_the_node_keeps_serving(graph):
    from pcc_ros.msg.stamps import ns_to_stamp
    from pcc_ros.runtime.dds import wait_for

    probe, got = graph["probe"], graph["got"]
    clouds = _read_topic(graph["bag"], "/points")
    dets = _read_topic(graph["bag"], "/detections")
    stamp0 = min(clouds)
    pub_cloud = probe.create_publisher("/points", CLOUD, SENSOR_DATA)
    pub_dets = probe.create_publisher("/detections", DETS, RELIABLE)
    assert wait_for(lambda: pub_cloud.matched() >= 2 and pub_dets.matched() >= 2, 30)

    def send_good(stamp_ns: int) -> None:
        good, det_good = _read_topic(graph["bag"], "/points")[stamp0], _read_topic(graph["bag"], "/detections")[stamp0]
        good.header.stamp = ns_to_stamp(stamp_ns)
        det_good.header.stamp = ns_to_stamp(stamp_ns)
        pub_cloud.publish(good)
        pub_dets.publish(det_good)

    def completed(stamp_ns: int) -> bool:
        return any(stamp_to_ns(m.header.stamp) == stamp_ns for m in got["completed"])

    # Warm-up frame: a new best-effort writer's first samples can precede the reader's side
    # of discovery; once one frame made the round trip, the path is established both ways.
    warm_stamp, bad_stamp, good_stamp = (s * 10**9 for s in (1_999_999_999, 2_000_000_000, 2_000_000_001))
    warmed = False
    for k in range(20):
        send_good(warm_stamp + k * 10**6)
        if _wait(lambda k=k: completed(warm_stamp + k * 10**6), 2.0):
            warmed = True
            break
    assert warmed
    before = len(got["completed"])
    bad = clouds[stamp0]
    bad.header.stamp = ns_to_stamp(bad_stamp)
    bad.data = np.asarray(bad.data)[:1000]  # width/row_step claim 123k points, data holds 62
    det_bad = dets[stamp0]
    det_bad.header.stamp = ns_to_stamp(bad_stamp)
    pub_cloud.publish(bad)
    pub_dets.publish(det_bad)
    assert _wait(lambda: "skipped a frame" in graph["logs"]["completion"].read_text(), 10)
    send_good(good_stamp)
    assert _wait(lambda: completed(good_stamp), 30)
    stamps = [stamp_to_ns(m.header.stamp) for m in got["completed"][before:]]
    assert bad_stamp not in stamps
    assert all(p.poll() is None for p in graph["procs"])  # both nodes still running
    log = graph["logs"]["completion"].read_text()
    assert "skipped a frame" in log and "PointCloud2" in log


def test_echo_discovers_the_type_and_prints_filtered_detections(graph):
    from pcc_ros.msg.stamps import ns_to_stamp

    probe = graph["probe"]
    stamp0 = min(_read_topic(graph["bag"], "/points"))
    pub_cloud = probe.create_publisher("/points", CLOUD, SENSOR_DATA)
    pub_dets = probe.create_publisher("/detections", DETS, RELIABLE)
    echo = subprocess.Popen(
        ["timeout", "60", *PCC, "echo", "/detections_filtered", "--count", "1", "--timeout", "45"],
        env=graph["env"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
    )
    try:
        k = 0
        while echo.poll() is None and k < 80:  # volatile topics: keep sending until echo has matched
            cloud, dets = _read_topic(graph["bag"], "/points")[stamp0], _read_topic(graph["bag"], "/detections")[stamp0]
            stamp = ns_to_stamp((2_100_000_000 + k) * 10**9)
            cloud.header.stamp, dets.header.stamp = stamp, stamp
            pub_cloud.publish(cloud)
            pub_dets.publish(dets)
            k += 1
            time.sleep(0.5)
        out, err = echo.communicate(timeout=20)
    finally:
        if echo.poll() is None:
            os.killpg(echo.pid, signal.SIGKILL)
            echo.wait(timeout=5)
    assert echo.returncode == 0, err
    assert "Detection3DArray" in out and "velodyne" in out and "id=" in out
