"""Node shells: importable and introspectable without ROS; a live rclpy test where ROS exists."""

from __future__ import annotations

import importlib
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import live_pipeline_node, require_rclpy

from pcc_ros.pipeline.config import parameter_table, read_parameters

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("module", ["completion_node", "detection_filter_node"])
def test_node_modules_import_without_rclpy(module):
    mod = importlib.import_module(f"pcc_ros.nodes.{module}")
    assert callable(mod.main) and mod.NODE_NAME == module
    if importlib.util.find_spec("rclpy") is None:
        assert "rclpy" not in sys.modules


def test_parameter_table_covers_the_yaml_files_with_types_and_descriptions():
    table = {spec.name: spec for spec in parameter_table()}
    for name in ("completion", "detection_filter"):
        for key, value in read_parameters(REPO / "config" / f"{name}.yaml").items():
            spec = table[key]
            assert spec.description
            expected = {bool: "bool", int: "integer", float: "double", str: "string", list: "string_array"}[type(value)]
            assert spec.type_name == expected, key
    assert table["classes"].type_name == "string_array"
    assert table["match_threshold"].default == 0.3 and table["detection_threshold"].default == 0.5


@pytest.mark.ros
def test_completion_node_publishes_completed_cloud():
    """The node class in-process under real rclpy (the end-to-end test runs the installed processes)."""
    require_rclpy()
    from sensor_msgs.msg import PointCloud2

    from pcc_ros.msg.detections import detection_array_from_boxes
    from pcc_ros.msg.pointcloud2 import create_cloud
    from pcc_ros.nodes.ros_node import rclpy_classes
    from pcc_ros.types import Boxes

    rng = np.random.default_rng(0)
    pts = (rng.normal(size=(500, 3)) * [1.5, 0.7, 0.5] + [10, 0, -0.8]).astype(np.float32)
    boxes = Boxes([[10, 0, -0.8]], [[4, 1.7, 1.5]], [0.0], ["Car"], [0.9], ["1"])
    stamp = 1_000_000_000
    with live_pipeline_node("completion_node", "completion", {"backend": "mirror"}, "completed",
                            PointCloud2) as (_, exchange):
        got = exchange(create_cloud(pts, ["x", "y", "z"], "velodyne", stamp, rclpy_classes),
                       detection_array_from_boxes(boxes, "velodyne", stamp, rclpy_classes), timeout=10)
        assert got and got[0].header.frame_id == "velodyne"


@pytest.mark.parametrize(("ros_args", "expected"), [
    (["--params-file", "{tmp}/bad.yaml"], "bad.yaml:4:1: not valid YAML"),
    (["--params-file", "{tmp}/missing.yaml"], "missing.yaml: cannot read parameter file (No such file or directory)"),
    (["-p"], "Couldn't parse trailing -p flag"),
])
def test_a_bad_ros_args_line_stops_the_node_with_one_line_not_a_traceback(tmp_path, ros_args, expected):
    """rclpy.init refuses a malformed parameter file or --ros-args line with its own RCLError; the
    node says which file and line (as pcc replay does) and exits 1 instead of a Python traceback,
    in one line (rcl's parser is asked first: rclpy.init also logged a vaguer rcl line above it)."""
    require_rclpy()
    (tmp_path / "bad.yaml").write_text("/**/completion_node:\n  ros__parameters:\n    min_points: [1\n")
    code = "import sys; from pcc_ros.nodes.completion_node import main; sys.exit(main())"
    args = [a.format(tmp=tmp_path) for a in ros_args]
    out = subprocess.run([sys.executable, "-c", code, "--ros-args", *args], capture_output=True, text=True,
                         timeout=120, cwd=tmp_path)
    text = out.stdout + out.stderr
    assert out.returncode == 1, text
    assert "Traceback" not in text and expected in text, text
    fatal = [line for line in text.splitlines() if "FATAL" in line]
    assert len(fatal) == 1 and "/project/src" not in fatal[0], text
    # ours is the only line: rclpy.init's own "[rcl]: Failed to parse global arguments" came first
    assert text.strip().splitlines() == fatal, text


@pytest.mark.ros
def test_a_node_that_fails_to_start_leaves_no_log_handler_behind():
    """A parameter the node refuses stops its construction: the handler it put on the package's
    logger goes with it (else every later pipeline line is sent, once more per failed node, to a
    logger of a node that never ran)."""
    import logging

    rclpy = require_rclpy()
    from rclpy.parameter import Parameter

    from pcc_ros.errors import ConfigError
    from pcc_ros.nodes.ros_node import PipelineNode, RclpyLogHandler

    package = logging.getLogger("pcc_ros")
    rclpy.init()
    try:
        for _ in range(2):
            with pytest.raises(ConfigError, match="no_such_parameter"):
                PipelineNode("completion_node", "completion",
                             parameter_overrides=[Parameter("backend", value="mirror"),
                                                  Parameter("no_such_parameter", value=1)])
        assert not [h for h in package.handlers if isinstance(h, RclpyLogHandler)]
    finally:
        rclpy.try_shutdown()


@pytest.mark.ros
def test_the_pipelines_score_range_warning_is_a_node_log_line(capfd):
    """Scores outside [0, 1] with score_mapping identity (a detector's logits): the pipeline's warning
    is the node's ROS log line (severity, node name; so also on /rosout), not bare Python logging."""
    require_rclpy()
    from vision_msgs.msg import Detection3DArray

    from pcc_ros.msg.detections import detection_array_from_boxes
    from pcc_ros.msg.pointcloud2 import create_cloud
    from pcc_ros.nodes.ros_node import rclpy_classes
    from pcc_ros.types import Boxes

    pts = (np.random.default_rng(0).normal(size=(500, 3)) * [1.5, 0.7, 0.5] + [10, 0, -0.8]).astype(np.float32)
    boxes = Boxes([[10, 0, -0.8]], [[4, 1.7, 1.5]], [0.0], ["Car"], [3.2], ["1"])  # a logit
    with live_pipeline_node("detection_filter_node", "filter", {"backend": "mirror", "score_mapping": "identity"},
                            "detections_filtered", Detection3DArray) as (_, exchange):
        assert exchange(create_cloud(pts, ["x", "y", "z"], "velodyne", 10**9, rclpy_classes),
                        detection_array_from_boxes(boxes, "velodyne", 10**9, rclpy_classes), timeout=10)
    text = capfd.readouterr().err
    lines = [line for line in text.splitlines() if "outside [0, 1]" in line]
    assert len(lines) == 1 and lines[0].startswith("[WARN] ["), text
    assert "[detection_filter_node]: 1 detection scores" in lines[0], text


@pytest.mark.ros
def test_two_nodes_in_one_process_each_say_their_own_pipeline_lines_info_included(capfd):
    """The package's Python log records reach the ROS log through one bridge: a record goes to the
    node whose work logged it, once (two nodes in one process each forwarded every record: each
    line twice, the second under the other node's name), INFO included (the package logger, left at
    NOTSET, passed only warnings: INFO lines never reached the bridge); a record of no node's work
    goes to the oldest node. The last node gone, the package logger is as it was."""
    import logging

    require_rclpy()
    from rclpy.parameter import Parameter
    from vision_msgs.msg import Detection3DArray

    from pcc_ros.msg.detections import detection_array_from_boxes
    from pcc_ros.msg.pointcloud2 import create_cloud
    from pcc_ros.nodes.ros_node import PipelineNode, RclpyLogHandler, rclpy_classes
    from pcc_ros.runtime.node import working_for
    from pcc_ros.types import Boxes

    package = logging.getLogger("pcc_ros")
    pts = (np.random.default_rng(0).normal(size=(500, 3)) * [1.5, 0.7, 0.5] + [10, 0, -0.8]).astype(np.float32)
    boxes = Boxes([[10, 0, -0.8]], [[4, 1.7, 1.5]], [0.0], ["Car"], [3.2], ["1"])  # a logit: the pipeline warns
    with live_pipeline_node("detection_filter_node", "filter", {"backend": "mirror", "score_mapping": "identity"},
                            "detections_filtered", Detection3DArray) as (_, exchange):
        other = PipelineNode("completion_node", "completion", parameter_overrides=[
            Parameter("backend", value="mirror"), Parameter("score_mapping", value="sigmoid")])
        try:
            assert exchange(create_cloud(pts, ["x", "y", "z"], "velodyne", 10**9, rclpy_classes),
                            detection_array_from_boxes(boxes, "velodyne", 10**9, rclpy_classes), timeout=10)
            with working_for(other.get_logger()):  # as while its backend loads
                logging.getLogger("pcc_ros.models.base").info("a load line of the completion node")
            logging.getLogger("pcc_ros.msg.detections").info("a line of no node's work")
        finally:
            other.destroy_node()
    lines = capfd.readouterr().err.splitlines()

    def said(text: str) -> list[str]:
        return [line for line in lines if text in line]

    warned = said("outside [0, 1]")
    assert len(warned) == 1 and warned[0].startswith("[WARN] [") and "[detection_filter_node]: " in warned[0], lines
    info = said("a load line of the completion node")
    assert len(info) == 1 and info[0].startswith("[INFO] [") and "[completion_node]: " in info[0], lines
    oldest = said("a line of no node's work")
    assert len(oldest) == 1 and "[detection_filter_node]: " in oldest[0], lines
    assert package.level == logging.NOTSET and not [h for h in package.handlers if isinstance(h, RclpyLogHandler)]
