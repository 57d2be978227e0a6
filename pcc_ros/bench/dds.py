"""DDS runtime: cloud (de)serialisation speed, scan -> completed-cloud latency and loss over loopback.

1. serialise + deserialise a 120k-point PointCloud2 (x, y, z, intensity; 1.9 MB) through
   the runtime's wire classes (one-buffer ``data``) vs cyclonedds' element-by-element
   ``sequence<uint8>`` path, measured in the same process (target <= 5 ms); rosbags'
   ``serialize_cdr`` / ``deserialize_cdr`` as a reference row.
2. a ``pcc node completion --transport dds --backend mirror`` child process on a private
   localhost domain; this process publishes scans with 20 cars (best-effort, keep-last 5)
   and their detections at 10 Hz and receives the completed clouds: latency from
   publishing the scan to receiving its completed cloud (p50 / p95), and scans lost on the
   wire = published - received by the node (the node's ``/diagnostics`` counters; target 0).
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import time

import numpy as np

from pcc_ros.bench.common import median_ms, print_table

CLOUD = "sensor_msgs/msg/PointCloud2"
DETS = "vision_msgs/msg/Detection3DArray"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--points", type=int, default=120_000, help="points per scan")
    parser.add_argument("--cars", type=int, default=20, help="cars (detections) per scan")
    parser.add_argument("--frames", type=int, default=600, help="scans published at --hz")
    parser.add_argument("--hz", type=float, default=10.0)
    parser.add_argument("--skip-e2e", action="store_true", help="only the serialisation rows")


def synthetic_scan(n_points: int, n_cars: int, rng: np.random.Generator):
    """Ground plus ``n_cars`` box-shaped cars carrying ~250 returns each, and their Boxes."""
    from pcc_ros.boxes import Boxes

    angles = rng.uniform(-np.pi, np.pi, n_cars)
    ranges = rng.uniform(6, 40, n_cars)
    centers = np.stack([ranges * np.cos(angles), ranges * np.sin(angles), np.full(n_cars, -0.9)], axis=1)
    sizes = np.column_stack(
        [rng.uniform(3.8, 4.8, n_cars), rng.uniform(1.6, 1.9, n_cars), rng.uniform(1.4, 1.6, n_cars)]
    )
    yaws = rng.uniform(-np.pi, np.pi, n_cars)
    per_car = 250
    local = rng.uniform(-0.5, 0.5, size=(n_cars, per_car, 3)) * sizes[:, None, :]
    c, s = np.cos(yaws)[:, None], np.sin(yaws)[:, None]
    cars = np.stack([c * local[..., 0] - s * local[..., 1], s * local[..., 0] + c * local[..., 1], local[..., 2]], -1)
    cars = (cars + centers[:, None, :]).reshape(-1, 3)
    n_ground = max(0, n_points - len(cars))
    ground = np.column_stack([rng.uniform(-60, 60, (n_ground, 2)), rng.normal(-1.73, 0.02, n_ground)])
    xyz = np.concatenate([cars, ground]).astype(np.float32)
    points = np.column_stack([xyz, rng.uniform(0, 1, len(xyz)).astype(np.float32)])
    scores = rng.uniform(0.5, 1.0, n_cars)
    boxes = Boxes(centers, sizes, yaws, ["Car"] * n_cars, scores, [str(k) for k in range(n_cars)])
    return points, boxes


def serialisation_rows(n_points: int, rng: np.random.Generator) -> list[dict]:
    from pcc_ros.msg.pointcloud2 import create_cloud
    from pcc_ros.msg.typestore import get_typestore
    from pcc_ros.runtime import idl

    points = rng.normal(size=(n_points, 4)).astype(np.float32)
    msg = create_cloud(points, ["x", "y", "z", "intensity"], "velodyne", 1)
    store = get_typestore()
    wire = idl.serialize(CLOUD, msg)
    assert wire == bytes(store.serialize_cdr(msg, CLOUD))

    fast_ms = median_ms(lambda: idl.deserialize(CLOUD, idl.serialize(CLOUD, msg)), repeat=20)
    slow_cls = idl.idl_class(CLOUD, octets_as_buffer=False)
    fast_obj = idl.to_idl(CLOUD, msg)

    def element_by_element():
        obj = slow_cls(**{k: getattr(fast_obj, k) for k in fast_obj.__dataclass_fields__})
        obj.data = fast_obj.data.tolist()  # what the declared sequence<uint8> needs
        slow_cls.deserialize(obj.serialize())

    slow_ms = median_ms(element_by_element, repeat=3, warmup=1)
    rosbags_ms = median_ms(lambda: store.deserialize_cdr(store.serialize_cdr(msg, CLOUD), CLOUD), repeat=20)
    mb = len(wire) / 1e6
    return [
        {"path": "element-by-element sequence<uint8> (baseline)", "ms": slow_ms, "MB": mb, "speedup": 1.0},
        {"path": "one-buffer data (pcc_ros.runtime.idl)", "ms": fast_ms, "MB": mb, "speedup": slow_ms / fast_ms},
        {"path": "rosbags serialize_cdr + deserialize_cdr (ref)", "ms": rosbags_ms, "MB": mb,
         "speedup": slow_ms / rosbags_ms},
    ]


def end_to_end(args: argparse.Namespace, rng: np.random.Generator) -> dict:
    from pcc_ros.msg.detections import detection_array_from_boxes
    from pcc_ros.msg.pointcloud2 import create_cloud
    from pcc_ros.msg.stamps import stamp_to_ns
    from pcc_ros.runtime.base import RELIABLE, SENSOR_DATA
    from pcc_ros.runtime.dds import DdsRuntime, wait_for
    from pcc_ros.runtime.discovery import Discovery, rmem_max

    domain = 200 + os.getpid() % 30
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain), "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
    env.pop("CYCLONEDDS_URI", None)
    node = subprocess.Popen(
        [sys.executable, "-m", "pcc_ros.cli", "node", "completion", "--transport", "dds", "--backend", "mirror"],
        env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True,
    )
    runtime = DdsRuntime("pcc_bench_dds", discovery=Discovery.from_env(env))
    received: dict[int, int] = {}
    diagnostics: list = []
    try:
        runtime.create_subscription("/completed", CLOUD, lambda m: received.setdefault(
            stamp_to_ns(m.header.stamp), time.perf_counter_ns()), RELIABLE)
        runtime.create_subscription("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray", diagnostics.append, RELIABLE)
        runtime.start()
        pub_cloud = runtime.create_publisher("/points", CLOUD, SENSOR_DATA)
        pub_dets = runtime.create_publisher("/detections", DETS, RELIABLE)
        if not wait_for(lambda: pub_cloud.matched() and pub_dets.matched() and diagnostics, 120):
            raise RuntimeError("the node did not come up within 120 s")
        scenes = [synthetic_scan(args.points, args.cars, rng) for _ in range(10)]
        sent: dict[int, int] = {}
        period = 1.0 / args.hz
        start = time.perf_counter()
        for k in range(args.frames):
            stamp = 1_000_000_000 + k * int(period * 1e9)
            points, boxes = scenes[k % len(scenes)]
            cloud = create_cloud(points, ["x", "y", "z", "intensity"], "velodyne", stamp)
            dets = detection_array_from_boxes(boxes, "velodyne", stamp)
            delay = start + k * period - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
            sent[stamp] = time.perf_counter_ns()
            pub_dets.publish(dets)
            pub_cloud.publish(cloud)
        wait_for(lambda: len(received) >= len(sent), 5)
        diagnostics.clear()
        wait_for(lambda: diagnostics, 3)
    finally:
        runtime.shutdown()
        if node.poll() is None:
            os.killpg(node.pid, signal.SIGINT)
        try:
            node.wait(timeout=10)
        except subprocess.TimeoutExpired:
            os.killpg(node.pid, signal.SIGKILL)
            node.wait(timeout=5)
    values = {kv.key: kv.value for kv in diagnostics[-1].status[0].values} if diagnostics else {}
    latency = np.array([(received[s] - sent[s]) / 1e6 for s in received if s in sent])
    clouds_at_node = int(values.get("paired", 0)) + int(values.get("dropped_clouds", 0))
    return {
        "frames_published": len(sent),
        "completed_received": len(latency),
        "latency_p50_ms": float(np.percentile(latency, 50)) if len(latency) else float("nan"),
        "latency_p95_ms": float(np.percentile(latency, 95)) if len(latency) else float("nan"),
        "node_processing_p50_ms": float(values.get("latency_p50_ms", "nan")),
        "scans_lost_on_wire": len(sent) - clouds_at_node if values else None,
        "dropped_newest_wins": int(values.get("dropped_pairs_newest_wins", 0)),
        "net_core_rmem_max": rmem_max(),
    }


def run(args: argparse.Namespace) -> dict:
    rng = np.random.default_rng(args.seed)
    rows = serialisation_rows(args.points, rng)
    print_table(f"PointCloud2 serialise + deserialise, {args.points} points", rows)
    results: dict = {"serialisation": rows}
    if not args.skip_e2e:
        e2e = end_to_end(args, rng)
        print_table(
            f"scan -> completed cloud over loopback DDS ({args.hz:g} Hz, {args.cars} cars, {args.points} points)",
            [{"metric": k, "value": v} for k, v in e2e.items()],
        )
        results["end_to_end"] = e2e
    return results
