"""Shared fixtures: paths to the real sample data beside the repository; an isolated ROS 2 graph;
one tiny instance cache (``tiny_cache``) for the eval and train command tests."""

from __future__ import annotations

import importlib.util
import json
import os
import re
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
from shapes import car_with_cabin

from pcc_ros.data.instances import ExtractConfig, extract_instances
from pcc_ros.geometry.canonical import from_canonical
from pcc_ros.types import Boxes, Sample

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"
FASTDDS_PROFILE = REPO / "config" / "fastdds_large_data.xml"


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return REPO


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """``../shared/data`` (real KITTI / nuScenes samples); tests needing it skip without it."""
    if not SHARED_DATA.is_dir():
        pytest.skip("../shared/data is not present")
    return SHARED_DATA


@pytest.fixture(scope="session")
def tiny_cache(tmp_path_factory) -> Path:
    """A SynthCars-like instance cache: 2 sequences (train ``0000`` / test ``0001``) x 3 frames
    x 3 tracked cars at about 8, 25 and 45 m, each seen from the sensor's side only and thinned
    (30 %, 10 %, 3 % of the shape's points), with the complete shapes as ground truth.
    9 test instances (3 per distance band), 9 train instances, no validation carve-out."""
    root = tmp_path_factory.mktemp("synth")
    rng = np.random.default_rng(0)
    (root / "meta.json").write_text(json.dumps({"seed": 0, "splits": {"train": ["0000"], "test": ["0001"]}}))
    frames = []
    for seq in ["0000", "0001"]:
        shapes = {}
        for t in range(3):
            shapes[str(t)] = car_with_cabin(rng)
            (root / "shapes" / seq).mkdir(parents=True, exist_ok=True)
            np.save(root / "shapes" / seq / f"{t}.npy", shapes[str(t)])
        for f in range(3):
            centers = np.array([[1.0 + f, 8.0, -0.9], [-2.0 + f, -25.0, -0.9], [2.0, 45.0 + f, -0.9]])
            yaws = np.array([0.1, -0.2, 0.3 + 0.1 * f])
            lengths = np.array([4.2, 4.6, 3.9])
            size = np.column_stack([lengths, lengths * 0.4, lengths * 0.35])
            points = []
            for t in range(3):
                shape = shapes[str(t)]
                sensor = from_canonical(shape, centers[t], yaws[t], lengths[t])
                towards = -centers[t] / np.linalg.norm(centers[t])
                outward = sensor - centers[t]
                seen = (outward @ towards) > 0  # the sensor-facing half only
                keep = seen & (rng.random(len(shape)) < [0.3, 0.1, 0.03][t])
                points.append(sensor[keep])
            pts = np.concatenate(points).astype(np.float32)
            pts = np.column_stack([pts, np.zeros(len(pts), np.float32)])
            boxes = Boxes(centers, size, yaws, ["Car"] * 3, None, [str(t) for t in range(3)])
            frames.append(Sample(stamp_ns=f * 100_000_000, frame_id="velodyne", points=pts, ground_truth=boxes,
                                 sequence=seq, index=f))
    cache_dir = tmp_path_factory.mktemp("cache") / "cache"
    cache = extract_instances(frames, cache_dir, ExtractConfig(ground_margin=0.0, val_fraction=0.0), synthcars=root,
                              progress=False)
    assert len(cache.indices("test")) == 9 and len(cache.indices("train")) == 9
    return cache_dir


@pytest.fixture(autouse=True)
def _fresh_skip_log():
    """Each test starts with no invalid box skipped, so it sees the first ones logged in full
    (``pcc_ros.msg.detections`` logs a process's first 20 one by one, then at powers of ten)."""
    from pcc_ros.msg import detections

    detections._skipped[0] = 0


def require_rclpy():
    """``rclpy``; its absence fails the test, never skips it.

    `make setup` installs ROS 2 Jazzy into the venv (or defers to a sourced Jazzy), so every
    run of the suite has a real rclpy: the real-node tests must run wherever the suite does.
    """
    if importlib.util.find_spec("rclpy") is None:
        pytest.fail("rclpy does not import: run `make setup` (scripts/setup_ros.sh installs ROS 2 Jazzy "
                    "into the venv) or source a ROS 2 Jazzy install")
    import rclpy

    return rclpy


@contextmanager
def live_pipeline_node(node_name: str, mode: str, parameters: dict, output: str, output_type: type):
    """A ``PipelineNode`` under real rclpy beside a probe node that publishes its ``points`` and
    ``detections`` and records its ``output`` topic. Yields ``(node, exchange)``:
    ``exchange(cloud, dets, timeout)`` publishes the pair (again each second until discovery is
    through) and returns the ``output`` messages received. The nodes are destroyed before the
    context shuts down (a worker still publishing into a shut-down context would log "publisher's
    context is invalid")."""
    rclpy = require_rclpy()
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import PointCloud2
    from vision_msgs.msg import Detection3DArray

    from pcc_ros.nodes.ros_node import PipelineNode

    rclpy.init()
    node = probe = None
    try:
        node = PipelineNode(node_name, mode,
                            parameter_overrides=[Parameter(k, value=v) for k, v in parameters.items()])
        probe = rclpy.create_node("probe")
        got: list = []
        probe.create_subscription(output_type, output, got.append, 10)
        pub_cloud = probe.create_publisher(PointCloud2, "points", 10)
        pub_det = probe.create_publisher(Detection3DArray, "detections", 10)

        def exchange(cloud, dets, timeout: float) -> list:
            deadline = time.time() + timeout
            while not got and time.time() < deadline:
                pub_cloud.publish(cloud)
                pub_det.publish(dets)
                second = time.time() + 1.0
                while not got and time.time() < second:
                    for n in (node, probe):
                        rclpy.spin_once(n, timeout_sec=0.05)
            return got

        yield node, exchange
    finally:
        for n in (probe, node):
            if n is not None:
                n.destroy_node()
        rclpy.try_shutdown()


@pytest.fixture(scope="session", autouse=True)
def isolated_ros_graph(tmp_path_factory):
    """Every ROS 2 participant of the test session (in-process and child processes) on its own
    domain, discovering over loopback only, with the shipped large-data Fast DDS profile.

    The domain id comes from the pid, so parallel test sessions on one machine do not see
    each other's topics. The profile is the shipped ``config/fastdds_large_data.xml`` with
    the UDP transport limited to 127.0.0.1 (its custom transports replace the built-in ones,
    which ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` would otherwise restrict).
    """
    profile = tmp_path_factory.mktemp("fastdds") / "fastdds_large_data_loopback.xml"
    text = FASTDDS_PROFILE.read_text()
    text, n = re.subn(
        r"(<type>UDPv4</type>)",
        r"\1\n      <interfaceWhiteList><address>127.0.0.1</address></interfaceWhiteList>",
        text,
    )
    assert n == 1, "config/fastdds_large_data.xml: expected one UDPv4 transport"
    profile.write_text(text)
    values = {
        "ROS_DOMAIN_ID": str(10 + os.getpid() % 90),
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
        "FASTRTPS_DEFAULT_PROFILES_FILE": str(profile),
    }
    saved = {key: os.environ.get(key) for key in values}
    os.environ.update(values)
    yield values
    for key, value in saved.items():
        if value is None:
            os.environ.pop(key, None)
        else:
            os.environ[key] = value


def colcon_style_install(prefix: Path, work: Path) -> subprocess.CompletedProcess:
    """What colcon runs for an ament_python package: ``setup.py install`` into ``prefix``."""
    cmd = [
        sys.executable, "setup.py", "-q", "egg_info", "--egg-base", str(work),
        "build", "--build-base", str(work / "build"),
        "install", "--prefix", str(prefix), "--single-version-externally-managed",
        "--record", str(work / "record.txt"),
    ]
    # PCC_BUILD_KERNELS=0: the build's kernel compilation (~40 s) is left out; the installed nodes
    # find the kernels in the user's cache, keyed by the modules' content (pcc_ros.jit)
    env = {**os.environ, "PCC_BUILD_KERNELS": "0"}
    return subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, env=env)
