"""Real-data completion evaluation: track aggregation, real metrics, `pcc eval --real`."""

from __future__ import annotations

import json
from collections import Counter

import numpy as np
import pytest
from conftest import assert_named_failure, run_cli

from pcc_ros.data.track_aggregate import aggregate_clouds, collect_tracks, voxel_downsample
from pcc_ros.geometry.canonical import from_canonical
from pcc_ros.metrics.realdata import input_spacing, real_instance_metrics
from pcc_ros.types import Boxes, Sample


def _car_surface(rng: np.random.Generator, n: int = 3000) -> np.ndarray:
    """Points on the faces of a 4.0 x 1.8 x 1.5 m box, canonical units (length 1)."""
    half = np.array([0.5, 0.9 / 4.0, 0.75 / 4.0]) * 0.98  # strictly inside the box
    pts = rng.uniform(-1, 1, (n, 3)) * half
    axis = rng.integers(0, 3, n)
    pts[np.arange(n), axis] = np.sign(rng.uniform(-1, 1, n)) * half[axis]
    return pts


def _frame(index: int, canonical: np.ndarray, center, yaw: float, clutter: np.ndarray) -> Sample:
    size = np.array([4.0, 1.8, 1.5])
    sensor = from_canonical(canonical, np.asarray(center, float), yaw, size[0])
    points = np.concatenate([sensor, clutter]).astype(np.float32)
    boxes = Boxes(np.array([center], float), size[None], np.array([yaw]), np.array(["Car"], dtype=object),
                  np.ones(1), np.array(["7"], dtype=object))
    return Sample(stamp_ns=index * 100_000_000, frame_id="velodyne", points=points, ground_truth=boxes,
                 sequence="s", index=index)


def test_moving_car_aggregates_into_one_canonical_cloud():
    """A car that drives and turns between frames lines up exactly after box compensation."""
    rng = np.random.default_rng(0)
    shape = _car_surface(rng)
    front, back = shape[shape[:, 0] > 0.1], shape[shape[:, 0] < -0.1]  # each frame sees one part
    clutter = rng.uniform(30, 40, (200, 3))
    frames = [_frame(0, front, (10.0, 3.0, -0.8), 0.3, clutter), _frame(1, back, (14.0, 5.5, -0.7), 0.9, clutter)]
    skipped: Counter = Counter()
    tracks = collect_tracks(frames, ground_margin=0.0, skipped=skipped)
    assert list(tracks) == ["s/7"]
    track = tracks["s/7"]
    assert [o.frame for o in track.observations] == [0, 1]
    merged = track.aggregate()
    assert len(merged) == len(front) + len(back)
    expected = np.concatenate([front, back])
    d = np.linalg.norm(np.sort(merged, axis=0) - np.sort(expected, axis=0), axis=1)
    assert d.max() < 1e-4  # float32 round trip through the sensor frame
    assert len(track.aggregate(exclude=[1])) == len(front)


def test_voxel_downsample_one_point_per_cell():
    pts = np.array([[0.01, 0.01, 0.01], [0.02, 0.02, 0.02], [0.5, 0.5, 0.5]])
    out = voxel_downsample(pts, 0.1)
    assert len(out) == 2
    assert np.allclose(sorted(out[:, 0]), [0.015, 0.5])
    assert len(aggregate_clouds([pts, pts], voxel=0.1)) == 2
    with pytest.raises(ValueError):
        voxel_downsample(pts, 0.0)


def test_real_metrics_measure_floating_and_coverage():
    rng = np.random.default_rng(1)
    size = np.array([4.0, 1.8, 1.5])
    shape = _car_surface(rng)
    partial = shape[shape[:, 1] > 0.2]  # the left side only
    perfect = real_instance_metrics(shape, partial, shape, size)
    assert perfect["completeness"] == pytest.approx(0.0, abs=1e-9)
    assert perfect["fidelity"] == pytest.approx(0.0, abs=1e-9)
    assert perfect["inside_box"] == 1.0
    assert abs(perfect["bottom_gap"]) < 0.05 and abs(perfect["top_gap"]) < 0.05
    assert perfect["lateral_offset"] < 0.05
    # Lifted by 0.25 m (canonical 0.0625): floats above the bottom, sticks out of the top.
    lifted = shape + np.array([0, 0, 0.25 / 4.0])
    m = real_instance_metrics(lifted, partial, shape, size)
    assert m["bottom_gap"] == pytest.approx(perfect["bottom_gap"] + 0.25, abs=0.01)
    assert m["top_gap"] == pytest.approx(perfect["top_gap"] - 0.25, abs=0.01)
    assert m["inside_box"] < 0.9
    assert m["completeness"] > 0.1
    # The observed side alone: lopsided and incomplete, but perfectly faithful.
    side = real_instance_metrics(partial, partial, shape, size)
    assert side["fidelity"] == 0.0 and np.isnan(side["fidelity_generated"])
    assert side["lateral_offset"] > 0.8
    assert side["completeness"] > perfect["completeness"] + 0.3
    assert side["points"] == len(partial)
    assert input_spacing(np.zeros((1, 3))) != input_spacing(np.zeros((1, 3)))  # NaN for one point


@pytest.mark.slow
def test_pcc_eval_real_on_kitti(shared_data, tmp_path, capsys):
    from pcc_ros.cli.main import main

    out_json, out_png = tmp_path / "real.json", tmp_path / "real.png"
    rc = main(["eval", "--real", "--real-sources", f"{shared_data / 'kitti_tracking'},{shared_data / 'nuscenes_mini'}",
               "--backends", "input,mirror", "--json", str(out_json), "--plot", str(out_png), "--examples", "2"])
    assert rc == 0
    text = capsys.readouterr().out
    for metric in ("completeness", "fidelity", "side_cd", "inside_box", "bottom_gap", "top_gap", "points"):
        assert metric in text
    result = json.loads(out_json.read_text())
    assert result["instances"] >= 30  # two labelled vans over 20 frames
    nusc = next(v for k, v in result["sources"].items() if "nuscenes" in k)
    assert nusc["instances"] == 0 and nusc["skipped"]["track_too_short"] > 0  # one key frame only
    inp, mirror = result["backends"]["input"]["overall"], result["backends"]["mirror"]["overall"]
    assert mirror["completeness"] < inp["completeness"]  # the symmetric half covers more of the track
    assert mirror["lateral_offset"] == pytest.approx(0.0, abs=1e-6)  # symmetric by construction
    assert inp["lateral_offset"] > 0.1
    assert mirror["points_max"] > inp["points_max"]
    assert 0 < mirror["consistency"] < inp["consistency"] and mirror["consistency_pairs"] >= 30
    assert mirror["far_completeness"] < inp["far_completeness"]
    summary = {r["backend"]: r for r in result["summary"]}
    assert summary["mirror"]["generated_gain_vs_mirror"] == 0.0 and summary["input"]["lateral_balance"] > 0.1
    assert out_png.stat().st_size > 10_000


def test_pcc_eval_real_missing_source_is_a_clear_error(tmp_path, caplog):

    rc, text = run_cli(["eval", "--real", "--real-sources", tmp_path / "nope", "--backends", "input"], caplog)
    assert_named_failure(rc, text, tmp_path / "nope", "not found")


def test_context_backends_get_the_other_cars_of_the_same_frame():
    from pcc_ros.workflows.evaluate_real import scene_contexts

    def inst(frame: str, x: float) -> dict:
        return {"frame_key": frame, "center": np.array([x, 5.0, -0.8]), "size": np.array([4.0, 1.8, 1.5]),
                "yaw": 0.1, "label": "Car", "partial": np.full((5, 3), x / 100, dtype=np.float32)}

    instances = [inst("a", 10.0), inst("b", 20.0), inst("a", 30.0), inst("a", 40.0)]
    contexts = scene_contexts(instances)
    assert len(contexts[1].neighbour_boxes) == 0  # alone in its frame
    first = contexts[0]
    assert sorted(first.neighbour_boxes.center[:, 0].tolist()) == [30.0, 40.0]
    assert first.box.center[0, 0] == 10.0
    assert [p[0, 0] for p in first.neighbour_points] == pytest.approx([0.3, 0.4])


def test_detector_mode_contexts_hold_every_box_the_node_completes(shared_data):
    """With detector boxes the node gives a context backend every completed detection of the frame,
    false positives included; the evaluation does the same (not only the matched, scored ones)."""
    from pcc_ros.workflows.evaluate_real import node_crop, real_instances, scene_contexts

    instances, report = real_instances([shared_data / "kitti_tracking"], boxes="detections",
                                       detections_dir=shared_data / "kitti_tracking/detections/pointrcnn")
    assert report[str(shared_data / "kitti_tracking")]["skipped"]["detection_unmatched"] > 0
    contexts = scene_contexts(instances)
    per_frame = {}
    for inst in instances:
        per_frame[inst["frame_key"]] = per_frame.get(inst["frame_key"], 0) + 1
    richer = 0
    for inst, ctx in zip(instances, contexts):
        boxes, crops = inst["frame_scene"]
        assert len(ctx.neighbour_boxes) == len(boxes) - 1
        np.testing.assert_allclose(ctx.box.center[0], inst["center"])
        assert np.array_equal(crops[inst["scene_slot"]], inst["partial"])
        assert all(len(c) >= node_crop()[2] for c in crops)  # completion_node's min_points
        richer += len(boxes) > per_frame[inst["frame_key"]]
    assert richer > 0  # unmatched detections are neighbours too


def test_matched_labels_are_the_detector_rows_observations_with_label_boxes(shared_data):
    """--real-matched-labels: the observations the detector found, cropped from their labelled
    boxes, so labelled and detector rows can be compared on the same cars."""
    from pcc_ros.errors import ConfigError
    from pcc_ros.workflows.evaluate_real import real_instances

    src, det_dir = shared_data / "kitti_tracking", shared_data / "kitti_tracking/detections/pointrcnn"
    labels, _ = real_instances([src])
    det, _ = real_instances([src], boxes="detections", detections_dir=det_dir)
    paired, _ = real_instances([src], boxes="detections", detections_dir=det_dir, matched_labels=True)
    by_key = {i["key"]: i for i in labels}
    assert [i["key"].removesuffix("/label-of-det") for i in paired] == [i["key"].removesuffix("/det") for i in det]
    assert len(paired) < len(labels)  # the detector misses observations the labels have
    for inst in paired:
        same = by_key[inst["key"].removesuffix("/label-of-det")]
        np.testing.assert_array_equal(inst["partial"], same["partial"])
        np.testing.assert_array_equal(inst["reference"], same["reference"])
        np.testing.assert_allclose(inst["size"], same["size"])
    with pytest.raises(ConfigError, match="real-detections"):
        real_instances([src], matched_labels=True)


def test_mirrored_frames_show_each_car_from_its_other_flank(shared_data):
    """--real-mirror: the same observations, each crop and reference reflected in its box frame
    (y -> -y), the sensor on the other side; with detections too (their matching is unchanged)."""
    from scipy.spatial import cKDTree

    from pcc_ros.data.sources import open_frames
    from pcc_ros.workflows.evaluate_real import real_instances

    src, det_dir = shared_data / "kitti_tracking", shared_data / "kitti_tracking/detections/pointrcnn"
    for kwargs in ({}, {"boxes": "detections", "detections_dir": det_dir}):
        plain, _ = real_instances([src], **kwargs)
        mirrored, _ = real_instances([src], mirror=True, **kwargs)
        assert [i["key"] for i in mirrored] == [i["key"] for i in plain] and len(plain) > 10
        for a, b in zip(plain, mirrored):  # the same points (in another order)
            for cloud in ("partial", "reference"):
                assert len(b[cloud]) == len(a[cloud])
                assert cKDTree(a[cloud] * [1, -1, 1]).query(b[cloud])[0].max() < 1e-5
            np.testing.assert_allclose(b["origin"], np.asarray(a["origin"]) * [1, -1, 1], atol=1e-5)
    # both real tracks are seen from their left (+y); mirrored, from their right
    assert all(i["origin"][1] > 0 for i in plain) and all(i["origin"][1] < 0 for i in mirrored)
    frame = next(iter(open_frames(src)))
    twice = frame.mirrored().mirrored()
    np.testing.assert_array_equal(twice.points, frame.points)
    assert twice.ground_truth.equals(frame.ground_truth)


def test_a_named_backend_that_does_not_load_is_an_error_not_a_skip(tmp_path, monkeypatch):
    """`--backends pointpncnet --checkpoint pointpncnet=PATH` with a missing or damaged PATH fails
    naming it (it used to print empty tables and exit 0); only the default 'every available
    backend' run skips a backend whose shipped weights do not load."""
    import pcc_ros.workflows.evaluate_real as er
    from pcc_ros.errors import CheckpointError

    missing = {"pointpncnet": tmp_path / "nope.safetensors"}
    with pytest.raises(CheckpointError, match=r"nope\.safetensors"):  # a named checkpoint: always an error
        er.evaluate_real([], ["input", "pointpncnet"], missing, progress=False)

    def no_weights(name, checkpoint=None, **options):
        raise CheckpointError(f"{name}.safetensors: checkpoint weights not found")

    monkeypatch.setattr(er, "load_completer", no_weights)
    results, _ = er.evaluate_real([], ["pointpncnet"], {}, progress=False)  # every available backend: skipped
    assert "not found" in results["pointpncnet"]["skipped"]
    with pytest.raises(CheckpointError, match=r"pointpncnet\.safetensors"):  # --backends named it: an error
        er.evaluate_real([], ["pointpncnet"], {}, progress=False, strict=True)


def test_pcc_eval_real_with_a_missing_checkpoint_fails_naming_it(shared_data, tmp_path, caplog):
    from pcc_ros.cli.main import main

    out = tmp_path / "real.json"
    rc = main(["eval", "--real", "--real-sources", str(shared_data / "kitti_tracking"), "--backends", "pointpncnet",
               "--checkpoint", f"pointpncnet={tmp_path / 'nope.safetensors'}", "--json", str(out)])
    assert rc == 1 and "nope.safetensors" in caplog.text and "not found" in caplog.text
    assert not out.exists()
