"""Every ``pcc`` command runs to success on small data generated at test time (conftest's
``synthcars``: ``pcc synth``, 2 sequences x 4 low-res frames), so each works in every clone.

The commands whose success another test already runs are named in :data:`ELSEWHERE` (that
test must exist); a command in the registry without a success test here or there fails
:func:`test_every_command_has_a_test_that_runs_it_to_success`.
"""

from __future__ import annotations

import ast
import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import SYNTH_ARGS, SYNTH_SEQUENCE

from pcc_ros.cli.main import COMMANDS, main
from pcc_ros.pipeline.config import load_file

TEST_DIR = Path(__file__).resolve().parent

#: command -> the test (file::function) elsewhere that runs it to success.
ELSEWHERE = {
    "train": "test_train.py::test_real_scans_are_mixed_at_the_requested_share",
    "eval": "test_eval_cli.py::test_pcc_eval_aggregated_reference",
    "play": "test_ros_tools.py::test_play_through_the_nodes_matches_replay",
    "echo": "test_ros_tools.py::test_echo_finds_the_type_on_the_graph_and_prints_filtered_detections",
    "demo": "test_demo.py::test_demo_runs_end_to_end",
    "check-data": "test_check_data.py::test_cli_reports_and_exit_status",
}
#: command -> the test here that runs it to success.
HERE = {
    "synth": "test_synth_writes_the_dataset_the_other_commands_read",
    "convert": "test_convert_and_info_on_the_generated_bag",
    "info": "test_convert_and_info_on_the_generated_bag",
    "extract": "test_extract_writes_an_instance_cache",
    "eval-detections": "test_eval_detections_under_its_hyphenated_name",
    "calibrate-filter": "test_calibrate_filter_reproduces_from_its_seed_and_its_yaml_runs_in_a_node",
    "replay": "test_replay_records_the_completion_outputs",
    "bench": "test_bench_synth_with_one_frame",
}


def test_every_command_has_a_test_that_runs_it_to_success():
    assert set(HERE) | set(ELSEWHERE) == set(COMMANDS), set(COMMANDS) ^ (set(HERE) | set(ELSEWHERE))
    here = {node.name for node in ast.walk(ast.parse(Path(__file__).read_text())) if isinstance(node, ast.FunctionDef)}
    assert set(HERE.values()) <= here
    for command, where in ELSEWHERE.items():
        file, function = where.split("::")
        tree = ast.parse((TEST_DIR / file).read_text())
        assert function in {n.name for n in ast.walk(tree) if isinstance(n, ast.FunctionDef)}, (command, where)


def test_synth_writes_the_dataset_the_other_commands_read(synthcars):
    meta = json.loads((synthcars / "meta.json").read_text())
    assert meta["splits"] == {"train": ["0000"], "test": ["0001"]}
    assert meta["parameters"]["frames"] == int(SYNTH_ARGS[SYNTH_ARGS.index("--frames") + 1])
    for sequence in ("0000", "0001"):
        scans = sorted((synthcars / "training" / "velodyne" / sequence).glob("*.bin"))
        assert len(scans) == 4 and all(s.stat().st_size > 16 * 1000 for s in scans)  # x y z i float32
        assert len(list((synthcars / "detections" / "synthetic" / sequence).glob("*.txt"))) == 4
    assert list((synthcars / "shapes" / "0000").glob("*.npy"))


def test_convert_and_info_on_the_generated_bag(synth_bag, tmp_path, capsys):
    assert main(["info", str(synth_bag), "--json", str(tmp_path / "info.json")]) == 0
    printed = capsys.readouterr().out
    info = json.loads((tmp_path / "info.json").read_text())
    assert "/points" in printed and "/detections" in printed
    topics = info["topics"]
    assert {t: topics[t]["count"] for t in ("/points", "/detections", "/ground_truth")} == dict.fromkeys(
        ("/points", "/detections", "/ground_truth"), 4)
    assert topics["/detections"]["boxes_per_message"]["min"] > 0 and info["storage"] == "mcap"


def test_extract_writes_an_instance_cache(synthcars, tmp_path, monkeypatch):
    from pcc_ros.data.instances import InstanceCache
    from pcc_ros.workflows.evaluate import attach_families, instances_from_cache

    out = tmp_path / "cache"
    monkeypatch.chdir(synthcars.parent)  # relative paths, as in the docs' commands
    assert main(["extract", synthcars.name, "--synthcars", synthcars.name, "--out", str(out), "--no-progress"]) == 0
    cache = InstanceCache.load(out)
    assert len(cache.indices("test")) > 0 and len(cache.indices("train")) > 0
    # Evaluated from another directory, the cache still finds its SynthCars root's vehicle families.
    monkeypatch.chdir(tmp_path)
    instances, _ = instances_from_cache(cache, "test", None, 0)
    attach_families(cache, instances)
    assert instances and all(inst.meta.get("family") for inst in instances)


def test_eval_detections_under_its_hyphenated_name(synthcars, tmp_path, capsys):
    out = tmp_path / "eval.json"
    argv = ["eval-detections", "--kitti", str(synthcars), "--sequence", SYNTH_SEQUENCE, "--backend", "input",
            "--json", str(out)]
    assert main(argv) == 0
    assert "Operating curve" in capsys.readouterr().out
    result = json.loads(out.read_text())
    shipped = result["shipped_threshold"]
    assert result["frames"] == 4 and shipped["true_kept"] + shipped["true_lost"] == result["true"] > 0
    assert shipped["false_kept"] + shipped["false_removed"] == result["false"]


def test_calibrate_filter_reproduces_from_its_seed_and_its_yaml_runs_in_a_node(synthcars, synth_frames, tmp_path):
    """The YAML ``pcc calibrate-filter`` writes is the same file for the same seed, and a filter
    node core started from it runs with its weights and judges a generated frame with them."""
    from pcc_ros.msg.detections import detection_array_from_boxes
    from pcc_ros.msg.pointcloud2 import create_cloud
    from pcc_ros.pipeline.filter import false_probability
    from pcc_ros.runtime.base import RELIABLE, SENSOR_DATA
    from pcc_ros.runtime.local import LocalGraph, LocalRuntime
    from pcc_ros.runtime.node import NodeCore

    def calibrate(name: str) -> Path:
        out = tmp_path / f"{name}.yaml"
        argv = ["calibrate-filter", "--real", str(synthcars), "--real-detections",
                str(synthcars / "detections" / "synthetic"), "--real-sequence", "0000,0001", "--synth", str(synthcars),
                "--synth-frames", "4", "--folds", "2", "--seed", "3", "--out", str(out), "--json",
                str(tmp_path / f"{name}.json")]
        assert main(argv) == 0
        return out

    first, second = calibrate("a"), calibrate("b")
    text = first.read_text()
    assert text.replace(str(first), "OUT") == second.read_text().replace(str(second), "OUT")  # same seed, same file
    fitted = json.loads((tmp_path / "a.json").read_text())
    values = load_file(first, "detection_filter_node")  # the node's own parameter check
    block = yaml.safe_load(text)["/**/detection_filter_node"]["ros__parameters"]
    assert values["w_bias"] == block["w_bias"] == pytest.approx(fitted["bias"], abs=1e-4)
    assert values["reject_threshold"] == pytest.approx(fitted["threshold"], abs=1e-4)

    graph = LocalGraph(simulated=True)
    core = NodeCore(LocalRuntime(graph, "detection_filter_node"), "detection_filter_node", "filter",
                    {**values, "backend": "input"}, threaded=False)
    assert core.pipeline.config.filter.w_bias == values["w_bias"]
    kept, rejected = [], []
    probe = LocalRuntime(graph, "probe")
    dets_t = "vision_msgs/msg/Detection3DArray"
    probe.create_subscription("/detections_filtered", dets_t, kept.append, RELIABLE)
    probe.create_subscription("/detections_rejected", dets_t, rejected.append, RELIABLE)
    frame = synth_frames[0]
    probe.create_publisher("/points", "sensor_msgs/msg/PointCloud2", SENSOR_DATA).publish(
        create_cloud(frame.points, list(frame.fields), frame.frame_id, frame.stamp_ns))
    probe.create_publisher("/detections", dets_t, RELIABLE).publish(
        detection_array_from_boxes(frame.detections, frame.frame_id, frame.stamp_ns))
    assert len(kept) == len(rejected) == 1
    assert len(kept[0].detections) + len(rejected[0].detections) == len(frame.detections)
    # The decisions are the calibrated weights': the published terms through its logistic model.
    result = core.pipeline.process(frame.points, frame.detections)
    p_false = false_probability(result.filter_terms, core.pipeline.config.filter)
    judged = np.isfinite(p_false)
    assert judged.any()
    assert int((p_false[judged] > values["reject_threshold"]).sum()) == len(rejected[0].detections)


def test_replay_records_the_completion_outputs(synth_bag, tmp_path):
    from rosbags.highlevel import AnyReader

    from pcc_ros.msg.typestore import get_typestore

    out = tmp_path / "replayed"
    assert main(["replay", str(synth_bag), "--out", str(out), "--backend", "mirror"]) == 0
    with AnyReader([out], default_typestore=get_typestore()) as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
    assert counts["/completed"] == counts["/points"] == 4 and counts["/completed_markers"] == 4


def test_bench_synth_with_one_frame(tmp_path, capsys):
    """The one benchmark that needs no real scan, at its smallest (a figure, not a timing claim)."""
    out = tmp_path / "bench.json"
    assert main(["bench", "synth", "--frames", "1", "--json", str(out)]) == 0
    result = json.loads(out.read_text())
    assert result["frames_per_s"] > 0 and result["rays"] > 100_000 and result["points_per_frame"] > 10_000
    assert "generate end to end" in capsys.readouterr().out
