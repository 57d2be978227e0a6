"""Shared fixtures: paths to the real sample data beside the repository; an isolated ROS 2 graph."""

from __future__ import annotations

import importlib.util
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

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
    return subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
