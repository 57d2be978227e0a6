"""ROS 2 Jazzy in the venv (scripts/setup_ros.sh): vision_msgs built with upstream's type hashes, cached set-up."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import REPO, require_rclpy

from pcc_ros.msg.typestore import BUILT_PACKAGES, type_hash

WHEELS_STAMP = Path(sys.prefix) / ".pcc_ros-ros-wheels"
VISION_STAMP = Path(sys.prefix) / ".pcc_ros-vision_msgs"
from_wheels = pytest.mark.skipif(
    not WHEELS_STAMP.exists(), reason="ROS 2 comes from a sourced install, not from the wheels in this venv"
)


@pytest.mark.ros
@pytest.mark.parametrize("package", sorted(BUILT_PACKAGES))
def test_built_message_packages_have_upstream_rihs01_hashes(package):
    """The generated type descriptions hash exactly as upstream vision_msgs 4.1 and tf2_msgs
    (wire-compatible: the nodes' /tf readers match any Jazzy tf broadcaster)."""
    require_rclpy()
    from ament_index_python.packages import get_package_share_directory

    share = Path(get_package_share_directory(package))
    for name in BUILT_PACKAGES[package]:
        description = json.loads((share / "msg" / f"{name.rsplit('/', 1)[1]}.json").read_text())
        hashes = {h["type_name"]: h["hash_string"] for h in description["type_hashes"]}
        assert hashes[name] == type_hash(name), name
    # Upstream's published values, independent of this project's type store.
    assert type_hash("vision_msgs/msg/Detection3DArray") == (
        "RIHS01_793f5eab9595ac1c0da07873cc859db42eae51f0ee76056db8562515d830e018"
    )
    assert type_hash("tf2_msgs/msg/TFMessage") == (
        "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087"
    )


@pytest.mark.ros
def test_the_middleware_announces_the_upstream_hash():
    """What another ROS 2 Jazzy participant sees on the graph for a Detection3DArray publisher."""
    rclpy = require_rclpy()
    from rclpy.signals import SignalHandlerOptions
    from vision_msgs.msg import Detection3DArray

    context = rclpy.Context()
    rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node("pcc_hash_probe", context=context)
    try:
        node.create_publisher(Detection3DArray, "/pcc_hash_probe", 1)
        deadline = time.monotonic() + 10
        infos = []
        while not infos and time.monotonic() < deadline:
            infos = node.get_publishers_info_by_topic("/pcc_hash_probe")
            time.sleep(0.05)
        assert infos and str(infos[0].topic_type_hash) == type_hash("vision_msgs/msg/Detection3DArray")
        assert infos[0].topic_type == "vision_msgs/msg/Detection3DArray"
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=context)


@from_wheels
def test_wheels_export_files_point_at_local_include_dirs():
    import sysconfig

    import numpy

    files = sorted((Path(sys.prefix) / "share").glob("*/cmake/*__rosidl_generator_pyExport.cmake"))
    assert len(files) >= 10  # every message package of the wheels, plus vision_msgs
    for path in files:
        dirs = re.search(r'INTERFACE_INCLUDE_DIRECTORIES "([^"]*)"', path.read_text()).group(1).split(";")
        assert sysconfig.get_paths()["include"] in dirs and numpy.get_include() in dirs, path
        assert all(Path(d).is_dir() for d in dirs), (path, dirs)


@from_wheels
def test_the_venv_runs_rclpy_without_sourcing_anything():
    """A bare interpreter of the venv (no activation, no setup.bash) has what rclpy needs."""
    dropped = ("AMENT_PREFIX_PATH", "RMW_IMPLEMENTATION", "LD_LIBRARY_PATH", "_ROS_WHEELS_BOOTSTRAP_COMPLETE")
    env = {k: v for k, v in os.environ.items() if k not in dropped}
    code = (
        "import os, sys, rclpy, vision_msgs.msg, tf2_msgs.msg; "
        "from ament_index_python.packages import get_package_share_directory as share; "
        "print(os.environ['RMW_IMPLEMENTATION'], sys.prefix in os.environ['AMENT_PREFIX_PATH'].split(os.pathsep), "
        "share('vision_msgs').startswith(sys.prefix))"
    )
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["rmw_fastrtps_cpp", "True", "True"]


@from_wheels
@pytest.mark.slow
def test_second_setup_rebuilds_nothing():
    before = VISION_STAMP.stat().st_mtime_ns
    tic = time.monotonic()
    out = subprocess.run(
        ["bash", "scripts/setup_ros.sh", sys.prefix], cwd=REPO, capture_output=True, text=True, timeout=600
    )
    assert out.returncode == 0, out.stderr
    assert "up to date" in out.stdout and "building" not in out.stdout and "installing" not in out.stdout
    assert VISION_STAMP.stat().st_mtime_ns == before
    assert time.monotonic() - tic < 60


@pytest.mark.ros
def test_setup_defers_to_a_sourced_ros_install_and_refuses_another_distro():
    """ROS_DISTRO=jazzy: the sourced install is used, nothing installed; another distro: a clear refusal."""
    require_rclpy()
    script = ["bash", "scripts/setup_ros.sh", sys.prefix]
    jazzy = subprocess.run(script, cwd=REPO, env={**os.environ, "ROS_DISTRO": "jazzy"},
                           capture_output=True, text=True, timeout=120)
    assert jazzy.returncode == 0 and jazzy.stdout == "", jazzy.stderr
    humble = subprocess.run(script, cwd=REPO, env={**os.environ, "ROS_DISTRO": "humble"},
                            capture_output=True, text=True, timeout=120)
    assert humble.returncode == 1 and "ROS_DISTRO=humble" in humble.stderr and "Jazzy" in humble.stderr


@pytest.mark.ros
def test_every_topic_type_hashes_as_the_installed_ros_packages_describe_it():
    """Every message type on the nodes' topics: the project's type store (which writes the bags
    and decodes the wire) gives the RIHS01 hash that rosidl computed for the installed ROS 2
    package (its share/<package>/msg/<Type>.json), not a value pasted into the test."""
    require_rclpy()
    from ament_index_python.packages import get_package_share_directory

    from pcc_ros.msg.typestore import type_hash
    from pcc_ros.runtime.node import INPUTS, OUTPUTS

    types = {*INPUTS.values(), *(t for mode in OUTPUTS.values() for t in mode.values()),
             "diagnostic_msgs/msg/DiagnosticArray"}
    assert len(types) >= 4
    for name in sorted(types):
        package, _, message = name.split("/")
        description = json.loads((Path(get_package_share_directory(package)) / "msg" / f"{message}.json").read_text())
        hashes = {h["type_name"]: h["hash_string"] for h in description["type_hashes"]}
        assert hashes[name] == type_hash(name), name
