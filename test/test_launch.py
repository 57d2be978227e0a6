"""launch/perception.launch.py's own code, run against recording stand-ins: what it asks for.

This is not a launch: ``launch`` and ``launch_ros`` are not published on PyPI (no
ros-jazzy-launch wheels; the PyPI project named ``launch`` is unrelated), so these tests run
the launch file's own code — ``generate_launch_description()`` and the ``OpaqueFunction``
that builds the nodes — against minimal stand-ins that record what the file asks for
(``DeclareLaunchArgument``, ``OpaqueFunction``, ``launch_ros.actions.Node``),
then checks the result against the package itself: the executables are console scripts in
setup.py, the parameter files exist and every value passes the node core's parameter check.
Nothing here starts a process; the nodes themselves run under real rclpy in test_ros_e2e.py
and test_ros_tools.py. Where the real ``launch_ros`` is importable (a ROS 2 install) the file
is also loaded by it; elsewhere that test skips saying so.
"""

from __future__ import annotations

import importlib.util
import re
import sys
import types
from pathlib import Path

import pytest

from pcc_ros.pipeline.config import node_parameters, read_parameters
from pcc_ros.runtime.node import OUTPUTS

REPO = Path(__file__).resolve().parents[1]
LAUNCH_FILE = REPO / "launch" / "perception.launch.py"
EXPECTED_ARGUMENTS = {
    "params_file", "namespace", "points", "detections", "outputs", "backend", "device", "score_mapping",
    "use_sim_time", "rviz", "managed", "autostart",
}


class _Recorded:
    def __init__(self, *args, **kwargs):
        self.args, self.kwargs = args, kwargs


class _OpaqueFunction(_Recorded):
    def execute(self, context):
        return self.kwargs["function"](context)


def _stand_ins(share: Path) -> dict[str, types.ModuleType]:
    modules = {name: types.ModuleType(name) for name in (
        "launch", "launch.actions", "launch_ros", "launch_ros.actions",
        "ament_index_python", "ament_index_python.packages",
    )}
    modules["launch"].LaunchDescription = lambda entities: list(entities)
    modules["launch.actions"].DeclareLaunchArgument = type("DeclareLaunchArgument", (_Recorded,), {})
    modules["launch.actions"].OpaqueFunction = _OpaqueFunction
    modules["launch_ros.actions"].Node = type("Node", (_Recorded,), {})
    modules["launch_ros.actions"].LifecycleNode = type("LifecycleNode", (_Recorded,), {})

    def get_package_share_directory(package):
        assert package == "pcc_ros"
        return str(share)

    modules["ament_index_python.packages"].get_package_share_directory = get_package_share_directory
    return modules


@pytest.fixture
def recorded_launch(monkeypatch, tmp_path):
    """``run(**arguments)`` -> the processes the launch file starts, as recorded keyword dicts."""
    share = REPO  # the source tree has the install's layout for config/ (share/pcc_ros/config)
    for name, module in _stand_ins(share).items():
        monkeypatch.setitem(sys.modules, name, module)
    spec = importlib.util.spec_from_file_location("perception_launch", LAUNCH_FILE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    entities = module.generate_launch_description()
    declared = {e.args[0]: e.kwargs for e in entities if type(e).__name__ == "DeclareLaunchArgument"}
    opaque = [e for e in entities if isinstance(e, _OpaqueFunction)]

    def run(**arguments):
        unknown = set(arguments) - set(declared)
        assert not unknown, f"not launch arguments: {unknown}"
        values = {name: kw["default_value"] for name, kw in declared.items()}
        values.update(arguments)
        context = types.SimpleNamespace(launch_configurations=values)
        return [{**node.kwargs, "action": type(node).__name__}
                for function in opaque for node in function.execute(context)]

    run.declared = declared
    return run


def _console_scripts() -> set[str]:
    text = (REPO / "setup.py").read_text()
    return set(re.findall(r'"(\w+) = pcc_ros\.', text))


def test_every_argument_the_file_declares_is_documented(recorded_launch):
    assert set(recorded_launch.declared) == EXPECTED_ARGUMENTS
    doc = LAUNCH_FILE.read_text().split('"""')[1]
    nodes_doc = (REPO / "docs" / "nodes.md").read_text()
    for name, kwargs in recorded_launch.declared.items():
        assert kwargs["description"], name
        assert f"``{name}``" in doc, f"{name} missing from the launch file's docstring"
        assert f"`{name}`" in nodes_doc, f"{name} missing from docs/nodes.md"


def test_defaults_ask_for_both_nodes_with_the_shipped_parameter_files(recorded_launch):
    processes = recorded_launch()
    assert [p["executable"] for p in processes] == ["completion_node", "detection_filter_node"]
    assert {p.pop("action") for p in processes} == {"Node"}
    assert {p["executable"] for p in processes} <= _console_scripts()
    for process in processes:
        params_file, overrides = process["parameters"]
        assert Path(params_file).is_file() and Path(params_file).parent.name == "config"
        assert overrides == {"use_sim_time": False}
        # What rclpy would give the node: the file's block for this name, then the overrides.
        values = {**read_parameters(params_file, process["name"]), **overrides}
        node_parameters(values)  # every key known, every value within its rule
        assert process["namespace"] == ""
        assert process["remappings"] == [("points", "points"), ("detections", "detections")]


def test_arguments_reach_the_recorded_node_actions(recorded_launch, tmp_path):
    params = tmp_path / "mine.yaml"
    params.write_text(
        "/**/completion_node:\n  ros__parameters:\n    min_points: 7\n"
        "/**/detection_filter_node:\n  ros__parameters:\n    match_threshold: 0.4\n"
    )
    processes = recorded_launch(
        params_file=str(params), namespace="/car1", points="/velodyne_points", detections="/detector/boxes",
        outputs="/perception/pcc", backend="mirror", device="cuda:0", score_mapping="sigmoid", use_sim_time="true",
    )
    assert len(processes) == 2
    for process in processes:
        assert process["namespace"] == "/car1"
        params_file, overrides = process["parameters"]
        assert params_file == str(params)
        assert overrides == {"use_sim_time": True, "backend": "mirror", "device": "cuda:0", "score_mapping": "sigmoid"}
        node_parameters({**read_parameters(params_file, process["name"]), **overrides})
        remaps = dict(process["remappings"])
        assert remaps["points"] == "/velodyne_points" and remaps["detections"] == "/detector/boxes"
        for topic in (*OUTPUTS["completion"], *OUTPUTS["filter"]):
            assert remaps[topic] == f"/perception/pcc/{topic}"
    assert read_parameters(params, "completion_node") == {"min_points": 7}


@pytest.mark.parametrize("autostart", ["true", "false"])
def test_managed_argument_asks_for_the_lifecycle_nodes(recorded_launch, autostart):
    """``managed:=true``: launch_ros' LifecycleNode with the managed entry points (console scripts
    of setup.py), the same parameters and remappings, autostart as asked."""
    plain = recorded_launch(points="/velodyne_points")
    processes = recorded_launch(points="/velodyne_points", managed="true", autostart=autostart)
    assert [p["action"] for p in processes] == ["LifecycleNode", "LifecycleNode"]
    assert [p["executable"] for p in processes] == ["completion_node_managed", "detection_filter_node_managed"]
    assert {p["executable"] for p in processes} <= _console_scripts()
    for process, same in zip(processes, plain):
        assert process.pop("autostart") is (autostart == "true")
        assert {k: v for k, v in process.items() if k not in ("executable", "action")} == {
            k: v for k, v in same.items() if k not in ("executable", "action")}
    with pytest.raises(ValueError, match="managed"):
        recorded_launch(managed="maybe")


def test_rviz_argument_asks_for_rviz_with_the_shipped_config(recorded_launch):
    processes = recorded_launch(rviz="true")
    rviz = processes[-1]
    assert rviz["executable"] == "rviz2" and rviz["arguments"][0] == "-d"
    assert Path(rviz["arguments"][1]).is_file()
    with pytest.raises(ValueError, match="use_sim_time"):
        recorded_launch(use_sim_time="yes please")


def test_rviz_config_shows_the_node_outputs_with_their_fields():
    import yaml

    from pcc_ros.pipeline.outputs import COMPLETED_CLOUD_DTYPE

    config = yaml.safe_load((REPO / "config" / "pcc_ros.rviz").read_text())
    manager = config["Visualization Manager"]
    displays = manager["Displays"]
    topics = {d["Topic"]["Value"]: d for d in displays if "Topic" in d}
    assert {"/points", "/completed", "/completed_markers", "/filter_markers"} <= set(topics)
    clouds = [d for d in displays if d["Class"].endswith("/PointCloud2") and d["Topic"]["Value"] == "/completed"]
    assert {d["Color Transformer"] for d in clouds} == {"RGB8", "Intensity"}
    channels = {d["Channel Name"] for d in clouds if d["Color Transformer"] == "Intensity"}
    assert channels <= set(COMPLETED_CLOUD_DTYPE.names) and "rgb" in COMPLETED_CLOUD_DTYPE.names
    assert topics["/points"]["Topic"]["Reliability Policy"] == "Best Effort"  # hears any scan publisher
    assert manager["Global Options"]["Fixed Frame"] == "velodyne"
    setup = (REPO / "setup.py").read_text()
    assert 'glob("config/*.rviz")' in setup  # installed to share/pcc_ros/config


@pytest.mark.skipif(importlib.util.find_spec("launch_ros") is None,
                    reason="launch_ros absent: only a ROS 2 install has it (no ros-jazzy-launch-ros wheel on PyPI)")
def test_real_launch_loads_the_file():  # pragma: no cover - only on a ROS machine
    from launch.launch_description_sources import PythonLaunchDescriptionSource

    source = PythonLaunchDescriptionSource(str(LAUNCH_FILE))
    description = source.try_get_launch_description_without_context()
    names = {a.name for a in description.get_launch_arguments()}
    assert names == EXPECTED_ARGUMENTS
