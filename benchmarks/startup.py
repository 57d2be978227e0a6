"""Node start-up: process start to live subscriptions, cold and warm, from a fresh install prefix.

Installs pcc_ros colcon-style (``setup.py install`` into a fresh prefix; the build compiles the
shipped nodes' kernels into the package, :mod:`pcc_ros.runtime.kernel_cache`), makes the prefix
read-only (a read-only bind mount in a private mount namespace, ``unshare -m``: read-only even
for root; where that is not possible the run says so), then starts each node from its installed
entry point with the shipped YAML, as a user would:

* ``cold``: an empty user cache (a fresh ``XDG_CACHE_HOME``): the first start on a machine;
* ``warm``: the same cache again (the second start).

For each start: seconds from the process start to the node's subscriptions on the graph (seen
by an independent rclpy participant in this process: its publishers match the node's
``points`` and ``detections`` readers), the CPU seconds the node used until then (user + system,
from ``/proc``: what the start costs whatever else loads the machine), and then real KITTI
tracking frames (``../shared/data``, full scans with their PointRCNN detections) played at
10 Hz from that moment: how many the node answered, and the first answer's latency.
``--unbuilt`` also installs without the build-time kernels (``PCC_BUILD_KERNELS=0``) and times
its cold start: what every start cost before.
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared" / "data" / "kitti_tracking"
OUTPUT = {"completion_node": "/completed", "detection_filter_node": "/detections_filtered"}
CONFIG = {"completion_node": "completion.yaml", "detection_filter_node": "detection_filter.yaml"}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--nodes", default="completion_node,detection_filter_node", help="nodes to start")
    parser.add_argument("--frames", type=int, default=20, help="KITTI frames played after the subscriptions are live")
    parser.add_argument("--unbuilt", action="store_true", help="also: a cold start without build-time kernels")
    parser.add_argument("--timeout", type=float, default=240.0, help="seconds a node may take to come up")


def install(prefix: Path, work: Path, build_kernels: bool) -> float:
    """``setup.py install`` into ``prefix`` as colcon runs it; returns the seconds it took."""
    env = {**os.environ, "PCC_BUILD_KERNELS": "1" if build_kernels else "0"}
    work.mkdir(parents=True, exist_ok=True)
    tic = time.perf_counter()
    out = subprocess.run([sys.executable, "setup.py", "-q", "egg_info", "--egg-base", str(work), "build",
                          "--build-base", str(work / "build"), "install", "--prefix", str(prefix),
                          "--single-version-externally-managed", "--record", str(work / "record.txt")],
                         cwd=REPO, capture_output=True, text=True, env=env)
    if out.returncode:
        raise SystemExit(f"install failed:\n{out.stderr[-3000:]}")
    print("\n".join(line for line in out.stdout.splitlines() if "kernels" in line))
    return time.perf_counter() - tic


def read_only_wrapper(prefix: Path) -> list[str]:
    """The command prefix that runs a program with ``prefix`` mounted read-only (empty: cannot)."""
    if not shutil.which("unshare"):
        return []
    probe = subprocess.run(["unshare", "-m", "sh", "-c", f"mount --bind '{prefix}' '{prefix}' && mount -o "
                            f"remount,bind,ro '{prefix}' && ! touch '{prefix}/.w' 2>/dev/null"],
                           capture_output=True)
    if probe.returncode:
        return []
    script = f"mount --bind '{prefix}' '{prefix}' && mount -o remount,bind,ro '{prefix}' && exec \"$@\""
    return ["unshare", "-m", "sh", "-c", script, "sh"]


def kitti_messages(count: int):
    from pcc_ros.data.kitti import KittiTracking
    from pcc_ros.msg.detections import detection_array_from_boxes
    from pcc_ros.msg.pointcloud2 import create_cloud
    from pcc_ros.nodes.ros_node import rclpy_classes

    frames = list(KittiTracking(SHARED / "training").frames("0000", detections_dir=SHARED / "detections" / "pointrcnn"))
    frames = (frames * (count // len(frames) + 1))[:count]
    out = []
    for i, f in enumerate(frames):
        stamp = f.stamp_ns + i * 10**9 if i >= 20 else f.stamp_ns  # distinct stamps when repeated
        out.append((stamp, create_cloud(f.points, list(f.fields), f.frame_id, stamp, rclpy_classes),
                    detection_array_from_boxes(f.detections, f.frame_id, stamp, rclpy_classes)))
    return out


class Probe:
    """The independent participant: publishes scans and detections, records a node's answers."""

    def __init__(self, rclpy, output: str, output_type) -> None:
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
        from sensor_msgs.msg import PointCloud2
        from vision_msgs.msg import Detection3DArray

        self.node = rclpy.create_node("pcc_startup_probe")
        self.pub_points = self.node.create_publisher(PointCloud2, "/points", qos_profile_sensor_data)
        self.pub_detections = self.node.create_publisher(Detection3DArray, "/detections", 10)
        self.answers: dict[int, float] = {}
        self.lock = threading.Lock()
        self.node.create_subscription(output_type, output, self._answer,
                                      QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE))
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()

    def _answer(self, msg) -> None:
        with self.lock:
            self.answers.setdefault(msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec, time.perf_counter())

    def live(self) -> bool:
        return self.pub_points.get_subscription_count() >= 1 and self.pub_detections.get_subscription_count() >= 1

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()


def process_cpu_seconds(pid: int) -> float | None:
    """CPU seconds (user + system, all threads) a process has used so far: its start-up's cost
    independent of what else loads the machine (on an idle machine, about its wall time)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return round((int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK"), 2)


def start_once(node: str, prefix: Path, env: dict, wrapper: list[str], messages, timeout: float, rclpy) -> dict:
    """One start of ``node``: seconds to live subscriptions, frames answered, first answer latency."""
    import importlib

    module, _, cls = {"completion_node": "sensor_msgs.msg.PointCloud2",
                      "detection_filter_node": "vision_msgs.msg.Detection3DArray"}[node].rpartition(".")
    probe = Probe(rclpy, OUTPUT[node], getattr(importlib.import_module(module), cls))
    config = prefix / "share" / "pcc_ros" / "config" / CONFIG[node]
    cmd = [*wrapper, str(prefix / "lib" / "pcc_ros" / node), "--ros-args", "--params-file", str(config)]
    log = tempfile.TemporaryFile(mode="w+")
    tic = time.perf_counter()
    proc = subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        while not probe.live():
            if proc.poll() is not None or time.perf_counter() - tic > timeout:
                log.seek(0)
                raise SystemExit(f"{node} did not come up:\n{log.read()[-3000:]}")
            time.sleep(0.01)
        live = time.perf_counter() - tic
        cpu = process_cpu_seconds(proc.pid)
        sent = {}
        start = time.perf_counter()
        for i, (stamp, cloud, dets) in enumerate(messages):
            time.sleep(max(0.0, start + 0.1 * i - time.perf_counter()))
            sent[stamp] = time.perf_counter()
            probe.pub_points.publish(cloud)
            probe.pub_detections.publish(dets)
        deadline = time.perf_counter() + 20.0
        while len(probe.answers) < len(messages) and time.perf_counter() < deadline:
            time.sleep(0.05)
        with probe.lock:
            answered = {s: t for s, t in probe.answers.items() if s in sent}
        first = messages[0][0]
        result = {"subscriptions_live_s": round(live, 2), "cpu_s_to_live": cpu, "answered": len(answered),
                  "frames": len(messages),
                  "first_frame_answered": first in answered,
                  "first_answer_latency_ms": round((answered[first] - sent[first]) * 1e3, 1) if first in answered
                  else None}
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        probe.close()
        log.seek(0)
        text = log.read()
        log.close()
    if "Read-only file system" in text or "Traceback" in text:
        print(text[-3000:])
    return result


def run(args: argparse.Namespace) -> dict:
    from pcc_ros.tables import print_table

    nodes = [n.strip() for n in args.nodes.split(",") if n.strip()]
    work = Path(tempfile.mkdtemp(prefix="pcc_startup_"))
    domain = str(100 + os.getpid() % 100)
    graph_env = {"ROS_DOMAIN_ID": domain, "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
                 "FASTRTPS_DEFAULT_PROFILES_FILE": str(REPO / "config" / "fastdds_large_data.xml")}
    os.environ.update(graph_env)
    import rclpy

    rows, results = [], {}
    try:
        builds = [("built", True)] + ([("unbuilt", False)] if args.unbuilt else [])
        rclpy.init()
        messages = kitti_messages(args.frames)
        for label, kernels in builds:
            prefix = work / label / "install"
            seconds = install(prefix, work / label, kernels)
            wrapper = read_only_wrapper(prefix)
            print(f"installed ({label}) in {seconds:.0f} s into {prefix}; "
                  + ("read-only bind mount" if wrapper else "prefix WRITABLE (no unshare -m here)"))
            site = next((prefix / "lib").glob("python3*/site-packages"))
            for node in nodes:
                cache = work / label / f"cache-{node}"
                env = {k: v for k, v in os.environ.items() if k not in ("PCC_KERNEL_CACHE", "NUMBA_CACHE_DIR")}
                env.update(graph_env, PYTHONPATH=str(site), XDG_CACHE_HOME=str(cache), PYTHONUNBUFFERED="1",
                           AMENT_PREFIX_PATH=os.pathsep.join(filter(None, [str(prefix),
                                                                          os.environ.get("AMENT_PREFIX_PATH")])))
                for start in ("cold", "warm") if kernels else ("cold",):
                    r = start_once(node, prefix, env, wrapper, messages, args.timeout, rclpy)
                    r.update(install=label, read_only=bool(wrapper), install_s=round(seconds, 1))
                    results[f"{label}/{node}/{start}"] = r
                    rows.append({"install": label, "node": node, "start": start,
                                 "subscriptions live (s)": f"{r['subscriptions_live_s']:.2f}",
                                 "CPU s to live": r["cpu_s_to_live"],
                                 "answered": f"{r['answered']}/{r['frames']}",
                                 "first frame": "yes" if r["first_frame_answered"] else "NO",
                                 "first answer (ms)": r["first_answer_latency_ms"]})
    finally:
        rclpy.try_shutdown()
        shutil.rmtree(work, ignore_errors=True)
    print_table("node start-up (fresh install prefix, shipped YAML)", rows)
    return {"starts": results, "graph": graph_env}
