"""The real nodes under real ROS 2 Jazzy, end to end, on generated SynthCars frames (every
clone) and on the real KITTI frames (where ../shared/data is laid).

Both nodes are installed as colcon installs an ament_python package, started as separate
processes from their installed entry points (``lib/pcc_ros/completion_node`` ...), each in
its own session (a process started in the background of a non-interactive shell inherits
SIGINT as ignored until rclpy installs its handler, so readiness is awaited through the ROS
graph before any signal is sent). An independent rclpy participant in this process plays
4 generated SynthCars scans (conftest's ``synth_frames``) and the 20 KITTI tracking scans
(full size, ~120k points, x y z intensity) with their real PointRCNN detections at 10 Hz to
the same two running nodes and subscribes to every output; parameters come from YAML
files (``--params-file``) and ``-p``; the nodes stop on SIGINT with exit status 0.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import colcon_style_install, require_rclpy

from pcc_ros.geometry.boxes import points_in_boxes
from pcc_ros.msg.detections import boxes_from_detection_array
from pcc_ros.msg.pointcloud2 import read_xyz

pytestmark = [pytest.mark.ros, pytest.mark.slow]

PERIOD_S = 0.1  # 10 Hz, a Velodyne HDL-64E's rate
READY_TIMEOUT_S = 180.0  # torch + checkpoint load on a busy 2-core machine
NODES = ("completion_node", "detection_filter_node")
STAMPED_OUTPUTS = ("/completed", "/detections_filtered", "/detections_rejected")
OUTPUTS = (*STAMPED_OUTPUTS, "/completed_markers", "/filter_markers")


def _messages():
    from pcc_ros.msg.detections import detection_array_from_boxes
    from pcc_ros.msg.pointcloud2 import create_cloud
    from pcc_ros.nodes.ros_node import rclpy_classes

    return create_cloud, detection_array_from_boxes, rclpy_classes


@pytest.fixture(scope="module")
def kitti_frames(shared_data):
    from pcc_ros.data.kitti import KittiTracking

    root = shared_data / "kitti_tracking"
    frames = list(KittiTracking(root / "training").frames("0000", detections_dir=root / "detections" / "pointrcnn"))
    assert len(frames) == 20 and all(len(f.points) > 100_000 for f in frames)
    return frames


@pytest.fixture(scope="module")
def installed(tmp_path_factory, isolated_ros_graph):
    """pcc_ros installed colcon-style; the environment a sourced ``install/setup.bash`` gives."""
    work = tmp_path_factory.mktemp("colcon")
    prefix = work / "install"
    out = colcon_style_install(prefix, work)
    assert out.returncode == 0, out.stderr[-2000:]
    site = prefix / "lib" / f"python{sys.version_info.major}.{sys.version_info.minor}" / "site-packages"
    env = dict(os.environ)
    env["PYTHONPATH"] = str(site)  # the installed copy, not the source tree
    env["AMENT_PREFIX_PATH"] = os.pathsep.join(p for p in (str(prefix), env.get("AMENT_PREFIX_PATH", "")) if p)
    env["PYTHONUNBUFFERED"] = "1"
    env["RCUTILS_LOGGING_BUFFERED_STREAM"] = "0"
    env["OMP_NUM_THREADS"] = "1"  # two torch processes share the 2 cores with the player
    return prefix, env


class Graph:
    """The independent rclpy participant: publishes scans + detections, records every output."""

    def __init__(self, rclpy) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
        from rclpy.signals import SignalHandlerOptions
        from sensor_msgs.msg import PointCloud2
        from vision_msgs.msg import Detection3DArray
        from visualization_msgs.msg import MarkerArray

        self.rclpy = rclpy
        self.context = rclpy.Context()
        rclpy.init(context=self.context, signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node("pcc_test_player", context=self.context)
        reliable = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        # A LiDAR driver's QoS: best-effort keep-last 5 (what the node subscribes with by default).
        self.pub_points = self.node.create_publisher(PointCloud2, "/points", qos_profile_sensor_data)
        self.pub_detections = self.node.create_publisher(Detection3DArray, "/detections", 10)
        self.received: dict[str, list] = {}
        self.diagnostics_at: list[float] = []
        self.arrival: dict[str, dict[int, float]] = {}
        self.lock = threading.Lock()
        for topic, cls in (
            ("/completed", PointCloud2),
            ("/completed_markers", MarkerArray),
            ("/detections_filtered", Detection3DArray),
            ("/detections_rejected", Detection3DArray),
            ("/filter_markers", MarkerArray),
            ("/diagnostics", DiagnosticArray),
        ):
            self.received[topic] = []
            self.arrival[topic] = {}
            self.node.create_subscription(cls, topic, self._recorder(topic), reliable)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()

    def _recorder(self, topic):
        def record(msg) -> None:
            now = time.perf_counter()
            with self.lock:
                self.received[topic].append(msg)
                if topic == "/diagnostics":
                    self.diagnostics_at.append(now)
                header = getattr(msg, "header", None)
                if header is not None and topic != "/diagnostics":
                    stamp = header.stamp.sec * 10**9 + header.stamp.nanosec
                    self.arrival[topic].setdefault(stamp, now)

        return record

    def wait_for(self, predicate, timeout: float, procs=()) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if predicate():
                return True
            for proc in procs:
                if proc.poll() is not None:
                    return False
            time.sleep(0.1)
        return predicate()

    def parameters(self, node_name: str, names: list[str]) -> dict:
        """Values of ``names`` read from a running node's parameter service."""
        from rcl_interfaces.srv import GetParameters

        client = self.node.create_client(GetParameters, f"/{node_name}/get_parameters")
        assert client.wait_for_service(timeout_sec=20), f"{node_name}: no parameter service"
        future = client.call_async(GetParameters.Request(names=names))
        assert self.wait_for(future.done, 20), f"{node_name}: get_parameters timed out"
        self.node.destroy_client(client)
        values = future.result().values
        return {n: _parameter_value(v) for n, v in zip(names, values)}

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=2)
        self.node.destroy_node()
        self.rclpy.try_shutdown(context=self.context)


def _parameter_value(value):
    from rcl_interfaces.msg import ParameterType

    return {
        ParameterType.PARAMETER_BOOL: value.bool_value,
        ParameterType.PARAMETER_INTEGER: value.integer_value,
        ParameterType.PARAMETER_DOUBLE: value.double_value,
        ParameterType.PARAMETER_STRING: value.string_value,
        ParameterType.PARAMETER_STRING_ARRAY: list(value.string_array_value),
    }.get(value.type)


def start_node(executable: Path, args: list[str], env: dict, log: Path) -> subprocess.Popen:
    """One node from its installed entry point, in a new session (signals reach only it)."""
    with log.open("w") as out:
        return subprocess.Popen(
            [str(executable), "--ros-args", *args],
            env=env,
            stdout=out,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            start_new_session=True,
        )


def stop_node(proc: subprocess.Popen, log: Path) -> tuple[int, str]:
    """SIGINT (what Ctrl-C sends), then the exit status and the log."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    return proc.returncode, log.read_text()


#: Per frame source: the fixture of its frames and the completed points every run must at least give.
#: The real frames first, to nodes that have seen nothing else (``sensor: auto`` keeps the beam model
#: it estimated from the scans it saw); the generated ones run alone where the real data is absent.
SOURCES = {"kitti": ("kitti_frames", 10_000), "synth": ("synth_frames", 1_000)}


@pytest.fixture(scope="module")
def live_nodes(installed, tmp_path_factory):
    """Both nodes started from their installed entry points with YAML files and ``-p``, ready on
    the graph, and the test's player/recorder; stopped with SIGINT after the module's runs, which
    must end with exit status 0 and a log without an error."""
    rclpy = require_rclpy()
    prefix, env = installed
    tmp = tmp_path_factory.mktemp("ros_e2e")
    share = prefix / "share" / "pcc_ros" / "config"
    # A user's YAML for the filter: the shipped file's block with PointRCNN's logits mapped.
    filter_yaml = yaml.safe_load((share / "detection_filter.yaml").read_text())
    block = next(v for k, v in filter_yaml.items() if k.endswith("detection_filter_node"))
    block["ros__parameters"]["score_mapping"] = "sigmoid"
    (tmp / "filter.yaml").write_text(yaml.safe_dump(filter_yaml))
    commands = {
        "completion_node": ["--params-file", str(share / "completion.yaml"), "-p", "max_instances:=24"],
        "detection_filter_node": ["--params-file", str(tmp / "filter.yaml"), "-p", "min_points:=8"],
    }
    logs = {name: tmp / f"{name}.log" for name in NODES}
    procs = {name: start_node(prefix / "lib" / "pcc_ros" / name, commands[name], env, logs[name]) for name in NODES}
    graph = Graph(rclpy)
    nodes = {"graph": graph, "procs": procs, "logs": logs}
    try:
        # Ready = both nodes' subscriptions and publishers are on the graph (created after the
        # pipeline and its checkpoint loaded, so a ready node answers the first frame).
        ready = graph.wait_for(
            lambda: graph.pub_points.get_subscription_count() == 2
            and graph.pub_detections.get_subscription_count() == 2
            and graph.node.count_publishers("/completed") == 1
            and graph.node.count_publishers("/detections_filtered") == 1,
            READY_TIMEOUT_S,
            procs.values(),
        )
        if not ready:
            _fail(nodes, "the nodes did not come up")
        params = graph.parameters("completion_node", ["backend", "max_instances", "classes", "queue_size"])
        assert params == {"backend": "pointpncnet", "max_instances": 24, "classes": ["Car", "Van"], "queue_size": 2}
        params = graph.parameters("detection_filter_node", ["score_mapping", "min_points", "match_threshold"])
        assert params == {"score_mapping": "sigmoid", "min_points": 8, "match_threshold": 0.3}
        yield nodes
    finally:
        results = {name: stop_node(proc, logs[name]) for name, proc in procs.items()}
        graph.close()
    for name, (rc, log) in results.items():
        assert rc == 0, f"{name} exited {rc}:\n{log[-3000:]}"
        assert "Traceback" not in log and "ERROR" not in log, f"{name}:\n{log[-3000:]}"
        assert "ready" in log, log


def _fail(nodes, what: str) -> None:
    graph, logs = nodes["graph"], nodes["logs"]
    pytest.fail(f"{what}\noutputs: {_counts(graph)}\ndiagnostics: {_diagnostic_values(graph)}\n"
                + "\n".join(logs[name].read_text()[-2000:] for name in NODES))


@pytest.mark.parametrize("source", list(SOURCES))
def test_nodes_end_to_end_at_10hz(live_nodes, source, request, capsys):
    """Generated SynthCars frames (every clone) and the 20 real KITTI scans with PointRCNN's
    detections (where ../shared/data is laid) through the same two running nodes."""
    fixture, min_completed = SOURCES[source]
    frames = request.getfixturevalue(fixture)
    create_cloud, detection_array_from_boxes, classes = _messages()
    graph, procs = live_nodes["graph"], live_nodes["procs"]

    def fail(what: str) -> None:
        _fail(live_nodes, f"[{source}] {what}")

    with graph.lock:  # what an earlier source's run left
        for topic in OUTPUTS:
            graph.received[topic].clear()
            graph.arrival[topic].clear()
    sent: dict[int, float] = {}
    boxes_by_stamp = {}
    messages = []
    for frame in frames:
        cloud = create_cloud(frame.points, list(frame.fields), frame.frame_id, frame.stamp_ns, classes)
        dets = detection_array_from_boxes(frame.detections, frame.frame_id, frame.stamp_ns, classes)
        messages.append((frame.stamp_ns, cloud, dets))
        boxes_by_stamp[frame.stamp_ns] = frame.detections
    if source == "kitti":
        assert len(messages[0][1].data) > 1_800_000  # full-size scans (~1.9 MB each)
    n = len(messages)

    # Matched on our (writer) side does not mean the nodes' readers have matched us yet:
    # a handshake frame (stamped 1 s before the sequence, repeated until both nodes answer
    # it) proves the data path, and warms up the network's first inference.
    warm_stamp, frame0 = messages[0][0] - 10**9, frames[0]
    warm_cloud = create_cloud(frame0.points, list(frame0.fields), frame0.frame_id, warm_stamp, classes)
    warm_dets = detection_array_from_boxes(frame0.detections, frame0.frame_id, warm_stamp, classes)
    for _ in range(20):
        graph.pub_points.publish(warm_cloud)
        graph.pub_detections.publish(warm_dets)
        if graph.wait_for(lambda: _counts(graph)["/completed"] and _counts(graph)["/detections_filtered"], 2.0):
            break
    else:
        fail("no handshake frame came back")
    # Quiet until each node has published diagnostics after the handshake: the baseline.
    quiet = time.perf_counter() + 1.0
    time.sleep(1.0)
    if not graph.wait_for(lambda: len(_diagnostic_values(graph, since=quiet)) == 2, 10):
        fail("no diagnostics after the handshake")
    base = _diagnostic_values(graph, since=quiet)
    with graph.lock:
        for topic in OUTPUTS:
            graph.received[topic].clear()
            graph.arrival[topic].clear()

    tick = time.perf_counter()
    for i, (stamp, cloud, dets) in enumerate(messages):
        time.sleep(max(0.0, tick + i * PERIOD_S - time.perf_counter()))
        sent[stamp] = time.perf_counter()
        graph.pub_points.publish(cloud)
        graph.pub_detections.publish(dets)
    end = time.perf_counter()

    def delta(key: str) -> dict[str, int]:
        now = _diagnostic_values(graph, since=end)
        return {name: int(now[name][key]) - int(base[name][key]) for name in now}

    # Nothing may get lost in the middleware: every scan and detection array reaches both nodes.
    if not graph.wait_for(lambda: delta("scans_received") == dict.fromkeys(NODES, n)
                          and delta("detections_received") == dict.fromkeys(NODES, n), 30, procs.values()):
        fail("scans or detection arrays lost on the way")
    # Every frame answered, or - only where a node could not keep up - dropped by its
    # newest-wins hand-off and counted on /diagnostics (never silently lost).
    if not graph.wait_for(
        lambda: {name: delta("frames")[name] + delta("dropped_pairs_newest_wins")[name] for name in NODES}
        == dict.fromkeys(NODES, n)
        and _counts(graph) == {t: delta("frames")[_NODE_OF[t]] for t in OUTPUTS},
        60,
        procs.values(),
    ):
        fail("frames neither answered nor counted as dropped")
    dropped = delta("dropped_pairs_newest_wins")
    diagnostics = _diagnostic_values(graph, since=end)

    # The strict claim: at 10 Hz both nodes keep up and answer every frame. It holds where each
    # node's p95 latency is within the frame period (then a queue of two absorbs any spike) and
    # the machine is not starved by other jobs; otherwise the drops - counted on /diagnostics
    # and checked above to add up - are printed below instead of failing the run.
    load = os.getloadavg()[0]
    keeps_pace = all(float(diagnostics[name]["latency_p95_ms"]) <= PERIOD_S * 1000 for name in NODES)
    if load <= 2 * os.cpu_count() and keeps_pace:
        assert dropped == dict.fromkeys(NODES, 0), (dropped, load)
    for topic in STAMPED_OUTPUTS:  # each answer once, with its own frame's stamp
        stamps = [_stamp(m) for m in graph.received[topic]]
        assert len(set(stamps)) == len(stamps) and set(stamps) <= set(sent), topic

    # Completed points lie in the cars' boxes (instance = index of the detection in its frame).
    completed_points = 0
    for msg in graph.received["/completed"]:
        stamp = _stamp(msg)
        assert msg.header.frame_id == frame0.frame_id
        assert {"x", "y", "z", "instance"} <= {f.name for f in msg.fields}
        cloud = read_xyz(msg, ["instance"])
        boxes = boxes_by_stamp[stamp]
        instance = cloud[:, 3].astype(np.int64)
        assert instance.min(initial=0) >= 0 and instance.max(initial=0) < len(boxes)
        for i in np.unique(instance):
            pts = cloud[instance == i, :3]
            inside = points_in_boxes(pts, boxes[np.array([i])], margin=0.25)[0]
            assert len(inside) >= 0.95 * len(pts), (stamp, i, len(inside), len(pts))
        completed_points += len(cloud)
    assert completed_points > min_completed, completed_points

    # The filter splits every frame's detections into kept + rejected, untouched.
    rejected = 0
    filtered = {_stamp(m): m for m in graph.received["/detections_filtered"]}
    for rej in graph.received["/detections_rejected"]:
        kept = filtered[_stamp(rej)]
        both = np.concatenate([boxes_from_detection_array(kept).center, boxes_from_detection_array(rej).center])
        sent_centers = boxes_by_stamp[_stamp(rej)].center
        assert np.allclose(np.sort(both, axis=0), np.sort(sent_centers, axis=0), atol=1e-6)
        rejected += len(rej.detections)
    if source == "kitti":
        assert rejected > 0  # PointRCNN's real false positives with sigmoid-mapped scores

    assert all(len(m.markers) > 0 for m in graph.received["/completed_markers"])
    assert all(len(m.markers) > 0 for m in graph.received["/filter_markers"])

    # Latency as the test sees it (scan published -> output received) and the nodes' own p95.
    lines = []
    for topic in ("/completed", "/detections_filtered"):
        ms = np.array([(graph.arrival[topic][s] - sent[s]) * 1e3 for s in graph.arrival[topic]])
        lines.append(f"{topic}: {len(ms)}/{n} frames answered, end-to-end p50 {np.percentile(ms, 50):.1f} ms, "
                     f"p95 {np.percentile(ms, 95):.1f} ms")
    for name in NODES:
        values = diagnostics[name]
        lines.append(f"{name}: node latency p50 {values['latency_p50_ms']} ms, p95 {values['latency_p95_ms']} ms; "
                     f"{dropped[name]} pairs dropped (newest wins); no scan lost")
    lines.append(f"{rejected} detections rejected; load average {load:.1f} on {os.cpu_count()} cores")
    with capsys.disabled():
        print(f"\n[ros e2e, {n} {source} scans at 10 Hz] " + f"\n[ros e2e {source}] ".join(lines))


_NODE_OF = {
    "/completed": "completion_node",
    "/completed_markers": "completion_node",
    "/detections_filtered": "detection_filter_node",
    "/detections_rejected": "detection_filter_node",
    "/filter_markers": "detection_filter_node",
}


def _counts(graph: Graph) -> dict[str, int]:
    with graph.lock:
        return {t: len(graph.received[t]) for t in OUTPUTS}


def _stamp(msg) -> int:
    return msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec


def _diagnostic_values(graph: Graph, since: float = 0.0) -> dict[str, dict[str, str]]:
    """The latest diagnostics status of each node received after ``since``, as key -> value."""
    latest = {}
    with graph.lock:
        arrays = [a for a, at in zip(graph.received["/diagnostics"], graph.diagnostics_at) if at >= since]
    for array in arrays:
        for status in array.status:
            for name in NODES:
                if status.name == f"pcc_ros: {name}":
                    latest[name] = {kv.key: kv.value for kv in status.values}
    return latest
