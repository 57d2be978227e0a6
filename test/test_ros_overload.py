"""Overload on real ROS 2 Jazzy: full KITTI scans at 10 / 30 / 300 Hz into the installed
``completion_node`` (its own process, Fast DDS), then the publisher restarts.

The node's memory (VmRSS of its process) stays bounded, what it cannot process is counted on
``/diagnostics`` (``dropped_pairs_newest_wins``, ``dropped_clouds`` / ``dropped_detections``;
scans the best-effort transport itself lost show as ``scans_received`` below the sent
count), and after the publisher's participant is destroyed and a new one publishes stamps
from the beginning again, the node answers again. Each phase lasts ``PCC_OVERLOAD_SECONDS``
(default 4; the docs' figure was taken with 30).
"""

from __future__ import annotations

import os
import time

import pytest
from conftest import require_rclpy
from test_ros_e2e import READY_TIMEOUT_S, Graph, _messages, installed, kitti_frames, start_node, stop_node  # noqa: F401

pytestmark = [pytest.mark.ros, pytest.mark.slow]

PHASE_S = float(os.environ.get("PCC_OVERLOAD_SECONDS", "4"))
NODE = "completion_node"
#: The last phase's rate: above what the node can process on any machine (a real KITTI frame takes
#: it several milliseconds end to end; at 100 Hz an idle 2-core machine now keeps up), so the phase
#: is an overload wherever the test runs and its drops must be counted.
OVERLOAD_HZ = 300
COUNTERS = ("scans_received", "frames", "dropped_pairs_newest_wins", "dropped_clouds", "dropped_detections")


def rss_mb(pid: int) -> float:
    with open(f"/proc/{pid}/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmRSS:")) / 1e3


def latest(graph: Graph, since: float) -> dict[str, int]:
    with graph.lock:
        arrays = [a for a, at in zip(graph.received["/diagnostics"], graph.diagnostics_at) if at >= since]
    values = {}
    for array in arrays:
        for status in array.status:
            if status.name == f"pcc_ros: {NODE}":
                values = {kv.key: kv.value for kv in status.values}
    return {k: int(v) for k, v in values.items() if k in COUNTERS}


def publish(graph: Graph, messages: list, rate_hz: float, seconds: float, first_stamp: int, pid: int,
            rss: list[float]) -> int:
    from pcc_ros.msg.stamps import ns_to_stamp
    from pcc_ros.nodes.ros_node import rclpy_classes

    period, start, k = 1.0 / rate_hz, time.monotonic(), 0
    while time.monotonic() - start < seconds:
        cloud, dets = messages[k % len(messages)]
        stamp = ns_to_stamp(first_stamp + int(k * period * 1e9), rclpy_classes)
        cloud.header.stamp = stamp
        dets.header.stamp = stamp
        graph.pub_points.publish(cloud)
        graph.pub_detections.publish(dets)
        k += 1
        if k % 5 == 0:
            rss.append(rss_mb(pid))
        time.sleep(max(0.0, start + k * period - time.monotonic()))
    return k


def test_overload_on_rclpy_keeps_memory_bounded_counts_drops_and_recovers(installed, kitti_frames, tmp_path):  # noqa: F811
    rclpy = require_rclpy()
    create_cloud, detection_array_from_boxes, classes = _messages()
    prefix, env = installed
    share = prefix / "share" / "pcc_ros" / "config"
    log = tmp_path / f"{NODE}.log"
    proc = start_node(prefix / "lib" / "pcc_ros" / NODE, ["--params-file", str(share / "completion.yaml")], env, log)
    messages = [(create_cloud(f.points, list(f.fields), f.frame_id, f.stamp_ns, classes),
                 detection_array_from_boxes(f.detections, f.frame_id, f.stamp_ns, classes)) for f in kitti_frames[:5]]
    graph = Graph(rclpy)
    report: dict = {}
    try:
        assert graph.wait_for(lambda: graph.pub_points.get_subscription_count() == 1
                              and graph.node.count_publishers("/completed") == 1, READY_TIMEOUT_S, [proc]), \
            log.read_text()[-3000:]
        publish(graph, messages, 2, 3.0, 10**9, proc.pid, [])  # handshake / warm-up at 2 Hz
        assert graph.wait_for(lambda: graph.received["/completed"], 60, [proc]), log.read_text()[-3000:]
        stamp = 100 * 10**9
        for rate in (10, 30, OVERLOAD_HZ):
            rss: list[float] = []
            mark = time.perf_counter()
            time.sleep(1.2)
            before = latest(graph, mark)
            sent = publish(graph, messages, rate, PHASE_S, stamp, proc.pid, rss)
            stamp += 10**12
            time.sleep(5.0)  # the frame in flight finishes; one more diagnostics period
            after = latest(graph, time.perf_counter() - 1.5)
            delta = {k: after[k] - before[k] for k in COUNTERS}
            report[rate] = {"sent": sent, **delta, "rss_max_mb": round(max(rss), 1)}
            assert delta["frames"] >= 1, report
            received = delta["scans_received"]
            assert received <= sent
            # every received scan is answered or counted as dropped (paired scans newest-wins,
            # unpaired ones by the pairer); only the frame in flight may be unaccounted for
            accounted = delta["frames"] + delta["dropped_pairs_newest_wins"] + delta["dropped_clouds"]
            assert received - 2 <= accounted <= received + 2, report
        top = report[OVERLOAD_HZ]
        # the overload shows: scans the node dropped (counted) or the best-effort transport lost
        shed = top["dropped_pairs_newest_wins"] + top["dropped_clouds"] + top["sent"] - top["scans_received"]
        assert shed > 0, report
        assert top["rss_max_mb"] - report[10]["rss_max_mb"] < 300, report

        # the publisher's participant goes away; a new one starts its stamps from the beginning
        graph.close()
        time.sleep(2.0)
        graph = Graph(rclpy)
        assert graph.wait_for(lambda: graph.pub_points.get_subscription_count() == 1, 60, [proc])
        publish(graph, messages, 10, PHASE_S, 10**9, proc.pid, [])
        assert graph.wait_for(lambda: graph.received["/completed"], 60, [proc]), "no answer after the restart"
        report["restart"] = {"completed_after_restart": len(graph.received["/completed"])}
        print("rclpy overload", report)
    finally:
        graph.close()
        rc, text = stop_node(proc, log)
    assert rc == 0, text[-3000:]
    assert "Traceback" not in text
