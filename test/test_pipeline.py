"""The per-frame pipeline on synthetic frames, through rosbags message classes."""

from __future__ import annotations

import numpy as np
import pytest

from pcc_ros.errors import ConfigError, MessageError
from pcc_ros.models.registry import load_completer
from pcc_ros.msg.detections import boxes_from_detection_array, detection_array_from_boxes
from pcc_ros.msg.pointcloud2 import create_cloud, read_xyz
from pcc_ros.pipeline.config import read_parameters
from pcc_ros.pipeline.core import (
    RAW_POINT_INSTANCE,
    SOURCE_OBSERVED,
    Pipeline,
    PipelineConfig,
)
from pcc_ros.pipeline.filter import FilterConfig
from pcc_ros.pipeline.outputs import build_outputs
from pcc_ros.types import Boxes

REPO_CONFIG = __import__("pathlib").Path(__file__).resolve().parents[1] / "config"


def box_surface_points(rng, center, size, yaw, n=400):
    """Points on the visible (sensor-facing) half of a box's surface, in the scan frame."""
    half = np.asarray(size) / 2
    local = rng.uniform(-1, 1, (n, 3)) * half
    axis = rng.integers(0, 2, n)
    local[np.arange(n), axis] = -half[axis]  # rear and right faces
    local[: n // 4, 2] = half[2]  # roof
    c, s = np.cos(yaw), np.sin(yaw)
    rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    return local @ rot.T + center


def make_frame(seed: int = 0):
    rng = np.random.default_rng(seed)
    boxes = Boxes(
        center=[[10.0, 3.0, -0.9], [20.0, -4.0, -0.9], [15.0, 8.0, -0.9], [30.0, 0.0, -0.9]],
        size=[[4.0, 1.7, 1.5], [4.2, 1.8, 1.5], [4.0, 1.7, 1.5], [0.6, 0.6, 1.7]],
        yaw=[0.3, -0.5, 0.0, 0.0],
        label=["Car", "Car", "Car", "Pedestrian"],
        score=[0.9, 0.4, 0.3, 0.8],
        track_id=["1", "2", "3", "4"],
    )
    cars = [box_surface_points(rng, boxes.center[i], boxes.size[i], boxes.yaw[i]) for i in range(2)]
    ground = np.c_[rng.uniform(0, 40, (3000, 2)) - [0, 20], np.full(3000, -1.73)]
    points = np.concatenate([*cars, ground]).astype(np.float32)  # box 2 is empty space
    return points, boxes


@pytest.fixture(scope="module")
def pipeline():
    # The constructed scene has ground returns behind the cars (no LiDAR would see them): these
    # tests exercise the TraPCC shape-mismatch rule; the evidence rule has test_filter_evidence.py.
    config = PipelineConfig(backend="mirror", min_points=10, filter=FilterConfig(rule="trapcc"))
    return Pipeline(config, completer=load_completer("mirror"))


def test_completions_lie_around_their_boxes(pipeline):
    points, boxes = make_frame()
    result = pipeline.process(points, boxes, stamp_ns=5, frame_id="velodyne")
    assert result.completed_index.tolist() == [0, 1]
    for i in (0, 1):
        mine = result.completed_points[result.completed_instance == i]
        assert len(mine) > 0
        local = mine - boxes.center[i]
        assert np.all(np.abs(local[:, 2]) < boxes.size[i, 2])
        assert np.linalg.norm(local[:, :2], axis=1).max() < np.linalg.norm(boxes.size[i, :2]) / 2 + 0.3
    assert set(result.timings_ms) >= {"crop_ms", "complete_ms", "filter_ms"}


def test_statuses_other_class_and_empty_box(pipeline):
    points, boxes = make_frame()
    result = pipeline.process(points, boxes)
    # Empty-space detection with a low score (0.3) is rejected; the pedestrian passes untouched.
    assert result.status.tolist()[2:] == ["rejected", "skipped"]
    assert result.keep.tolist() == [True, True, False, True]
    assert result.mismatch[2] == 1.0 and np.isnan(result.mismatch[3])
    assert result.skipped == {"other class": 1}
    assert len(result.kept) + len(result.rejected) == len(boxes)


def test_include_input_points_and_instance_cap():
    points, boxes = make_frame()
    cfg = PipelineConfig(backend="input", min_points=10, max_instances=1, include_input_points=True)
    result = Pipeline(cfg, completer=load_completer("input")).process(points, boxes)
    # every scan point once: the completed car's own crop under its instance (include_observed_points,
    # the default), the rest as raw points
    raw = (result.completed_instance == RAW_POINT_INSTANCE).sum()
    observed = ((result.completed_instance == 0) & (result.completed_source == SOURCE_OBSERVED)).sum()
    assert observed == len(result.crops[0]) > 0 and raw + observed == len(points)
    assert result.completed_index.tolist() == [0]  # highest score only
    assert result.skipped["over max_instances"] == 2


def test_messages_round_trip_and_outputs(pipeline):
    points, boxes = make_frame()
    cloud = create_cloud(points, ["x", "y", "z"], "velodyne", 123, None)
    dets = detection_array_from_boxes(boxes, "velodyne", 123)
    result, originals = pipeline.process_messages(cloud, dets)
    outputs = build_outputs(result, originals)
    completed = outputs["completed"]
    assert [f.name for f in completed.fields] == ["x", "y", "z", "instance", "rgb", "score", "source"]
    assert read_xyz(completed).shape == (len(result.completed_points), 3)
    kept = boxes_from_detection_array(outputs["detections_filtered"])
    rejected = boxes_from_detection_array(outputs["detections_rejected"])
    assert len(kept) + len(rejected) == len(boxes)
    assert list(rejected.track_id) == ["3"]
    # The original detections are republished with their own hypotheses first, untouched, and
    # the filter's decision appended (pcc_filter/mismatch here: the TraPCC rule).
    first = outputs["detections_filtered"].detections[0]
    assert first.results[0] is originals[0].results[0] and first.bbox is originals[0].bbox
    assert first.id == originals[0].id and first.results[-1].hypothesis.class_id == "pcc_filter/mismatch"
    assert not any(r.hypothesis.class_id.startswith("pcc_filter") for r in originals[0].results)  # not mutated


def test_nan_box_is_skipped_and_counted(pipeline):
    points, boxes = make_frame()
    dets = detection_array_from_boxes(boxes, "velodyne", 1)
    dets.detections[1].bbox.center.position.x = float("nan")
    result, originals = pipeline.process_messages(create_cloud(points, ["x", "y", "z"], "velodyne", 1), dets)
    assert len(result.detections) == 3 and len(originals) == 3
    assert result.skipped["invalid detection"] == 1


def test_detections_in_another_frame_are_refused(pipeline):
    points, boxes = make_frame()
    cloud = create_cloud(points, ["x", "y", "z"], "velodyne", 1)
    with pytest.raises(MessageError, match="base_link"):
        pipeline.process_messages(cloud, detection_array_from_boxes(boxes, "base_link", 1))


def test_class_names_match_case_insensitively_and_by_last_dotted_part():
    points, boxes = make_frame()
    boxes.label[:] = ["vehicle.car", "CAR", "car", "human.pedestrian.adult"]
    cfg = PipelineConfig(backend="input", min_points=10)
    result = Pipeline(cfg, completer=load_completer("input")).process(points, boxes)
    assert result.skipped.get("other class") == 1 and result.completed_index.tolist() == [0, 1]


def test_malformed_cloud_raises_message_error(pipeline):
    points, boxes = make_frame()
    cloud = create_cloud(points, ["x", "y", "z"], "velodyne", 1)
    cloud.point_step = 8  # fields now run past the point
    with pytest.raises(MessageError):
        pipeline.process_messages(cloud, detection_array_from_boxes(boxes, "velodyne", 1))


@pytest.mark.parametrize("name", ["completion", "detection_filter"])
def test_shipped_yaml_configs_parse(name):
    values = read_parameters(REPO_CONFIG / f"{name}.yaml")
    config = PipelineConfig.from_dict(values)
    assert config.backend and config.classes


def test_unknown_parameter_is_reported():
    with pytest.raises(ConfigError, match="min_pionts"):
        PipelineConfig.from_dict({"min_pionts": 3})


@pytest.mark.slow
def test_shipped_backend_scores_false_detections_higher_on_synthcars(tmp_path):
    """With the shipped PointPnCNet, detections on clutter / empty space mismatch more than cars."""
    from pcc_ros.data.kitti import KittiTracking
    from pcc_ros.data.synthetic import generate
    from pcc_ros.workflows.demo import truly_vehicle

    generate(tmp_path, sequences=1, frames=3, seed=11, progress=False)
    config = PipelineConfig(device="cpu", min_points=5, max_instances=64, filter=FilterConfig(rule="trapcc"))
    pipeline = Pipeline(config)
    true_scores, false_scores = [], []
    frames = KittiTracking(tmp_path / "training").frames("0000", detections_dir=tmp_path / "detections" / "synthetic")
    for frame in frames:
        result = pipeline.process(frame.points, frame.detections)
        judged = np.isfinite(result.mismatch)
        truth = truly_vehicle(result.detections, frame.ground_truth)
        true_scores += result.mismatch[judged & truth].tolist()
        false_scores += result.mismatch[judged & ~truth].tolist()
    assert len(true_scores) > 10 and len(false_scores) > 2
    # The rule reads the mismatch's ranking (its threshold is calibrated); the scale moves with
    # each fine-tune of the weights, so the check is the rank separation, P(false > true).
    false, true = np.array(false_scores)[:, None], np.array(true_scores)[None, :]
    assert np.median(false_scores) > np.median(true_scores)
    assert (false > true).mean() + 0.5 * (false == true).mean() > 0.7


@pytest.mark.parametrize(("workers", "torch_threads", "expected"), [(1, 1, 1), (1, 2, 2), (3, 1, 3)])
def test_filter_measures_on_as_many_threads_as_the_completion(monkeypatch, workers, torch_threads, expected):
    """The evidence filter runs on the completion's CPU threads: ``workers``, or torch's intra-op
    threads when ``workers`` is 1; its terms do not depend on that."""
    import torch

    import pcc_ros.pipeline.core as core_module

    calls = []
    measure = core_module.filter_terms

    def spy(*args, workers=1, **kwargs):
        calls.append(workers)
        return measure(*args, workers=workers, **kwargs)

    monkeypatch.setattr(core_module, "filter_terms", spy)
    points, boxes = make_frame()
    cfg = PipelineConfig(backend="input", min_points=10, workers=workers)
    previous = torch.get_num_threads()
    torch.set_num_threads(torch_threads)
    try:
        result = Pipeline(cfg, completer=load_completer("input")).process(points, boxes)
    finally:
        torch.set_num_threads(previous)
    assert calls == [expected]
    single = Pipeline(PipelineConfig(backend="input", min_points=10, workers=1), completer=load_completer("input"))
    torch.set_num_threads(1)
    try:
        reference = single.process(points, boxes)
    finally:
        torch.set_num_threads(previous)
    np.testing.assert_array_equal(result.filter_score, reference.filter_score)
    assert list(result.status) == list(reference.status)


def test_completed_cloud_colours_scores_and_raw_points():
    """Each completed point carries its detection's palette colour (PCL's packed 0x00RRGGBB) and
    score; a raw scan point (instance -1) is grey with a NaN score; every field as given."""
    from types import SimpleNamespace

    from pcc_ros.pipeline.outputs import INSTANCE_PALETTE, RAW_POINT_RGB, completed_cloud_array

    instance = np.array([-1, 0, 1, 11, -1], dtype=np.int32)
    result = SimpleNamespace(
        completed_points=np.arange(15, dtype=np.float32).reshape(5, 3), completed_instance=instance,
        completed_source=np.array([0, 1, 1, 0, 0], dtype=np.uint8),
        detections=SimpleNamespace(score=np.linspace(0.1, 1.2, 12)))
    cloud = completed_cloud_array(result)
    rgb = cloud["rgb"].view(np.uint32)
    packed = [(int(r) << 16) | (int(g) << 8) | int(b) for r, g, b in
              (RAW_POINT_RGB, INSTANCE_PALETTE[0], INSTANCE_PALETTE[1], INSTANCE_PALETTE[11 % len(INSTANCE_PALETTE)],
               RAW_POINT_RGB)]
    assert rgb.tolist() == packed
    assert np.isnan(cloud["score"][[0, 4]]).all()
    np.testing.assert_array_equal(cloud["score"][1:4], np.float32(result.detections.score[[0, 1, 11]]))
    assert cloud["instance"].tolist() == instance.tolist() and cloud["source"].tolist() == [0, 1, 1, 0, 0]
    np.testing.assert_array_equal(np.c_[cloud["x"], cloud["y"], cloud["z"]], result.completed_points)
