"""The evidence terms of the detection filter on constructed scenes, and the calibration."""

from __future__ import annotations

import numpy as np
import pytest

from pcc_ros.errors import ConfigError
from pcc_ros.pipeline.filter import (
    SENSOR_PRESETS,
    FilterConfig,
    evidence,
    false_probability,
    filter_terms,
    score_logit,
)
from pcc_ros.types import Boxes

SENSOR = SENSOR_PRESETS["hdl64"]
GROUND_Z = -1.73


def cast(targets, sensor=SENSOR, max_range: float = 80.0) -> np.ndarray:
    """A synthetic scan: every beam of ``sensor`` (azimuth within +-60 deg) hits the first of a
    flat ground, a wall at x = 40 m and the axis-aligned boxes ``targets`` [(lo, hi), ...]."""
    el = sensor.ring_elevations()
    az = np.deg2rad(np.arange(-60.0, 60.0, sensor.azimuth_resolution_deg))
    e, a = np.meshgrid(el, az, indexing="ij")
    d = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1).reshape(-1, 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(d[:, 2] < 0, GROUND_Z / d[:, 2], np.inf)
        t = np.minimum(t, np.where(d[:, 0] > 0, 40.0 / d[:, 0], np.inf))
        for lo, hi in targets:
            lo, hi = np.asarray(lo, float), np.asarray(hi, float)
            t1, t2 = lo / d, hi / d
            tn = np.fmax.reduce(np.minimum(t1, t2), axis=1)
            tf = np.fmin.reduce(np.maximum(t1, t2), axis=1)
            hit = (tf >= tn) & (tn > 0)
            t = np.where(hit, np.minimum(t, tn), t)
    ok = np.isfinite(t) & (t < max_range)
    return (d[ok] * t[ok, None]).astype(np.float32)


CAR_LO, CAR_HI = (14.0, -0.9, GROUND_Z + 0.3), (18.2, 0.9, GROUND_Z + 1.5)  # a car body (no wheels)
BOX = Boxes([[16.1, 0.0, GROUND_Z + 0.75]], [[4.2, 1.8, 1.5]], [0.0], ["Car"], [0.3])


def test_free_space_empty_box_vs_box_with_a_car():
    empty_scan = cast([])
    car_scan = cast([(CAR_LO, CAR_HI)])
    empty, car = evidence(empty_scan, BOX), evidence(car_scan, BOX)
    # Rays through the empty box return from the ground and wall behind it...
    assert empty.n_pass[0] > 50 and empty.n_stop[0] == 0 and empty.n_in[0] == 0
    # ... those through the car end on it.
    assert car.n_stop[0] > 50 and car.n_pass[0] == 0 and car.n_in[0] > 100
    assert empty.terms["free_space"][0] > 4 and car.terms["free_space"][0] < -4
    # Returns vs a car's: the car gives about what the beam model expects of its box.
    assert car.terms["density"][0] > -1.0 > empty.terms["density"][0] + 3
    # Both stand on the ground.
    assert empty.terms["ground_gap"][0] < 0.1 and car.terms["ground_gap"][0] < 0.1


def test_occluded_box_is_not_called_empty():
    """A wall between the sensor and the box: no ray reaches it, so no free-space evidence and
    no expected returns (the occluded share of the rays is discounted)."""
    wall = ((8.0, -4.0, GROUND_Z), (8.3, 4.0, 3.0))
    ev = evidence(cast([wall]), BOX)
    assert ev.n_pass[0] == 0 and ev.n_stop[0] == 0 and ev.n_occluded[0] > 50
    assert abs(ev.terms["free_space"][0]) < 1e-9
    assert abs(ev.terms["density"][0]) < 0.5  # expected * visible ~ 0: nothing is missing


def test_floating_box_has_a_ground_gap():
    lifted = Boxes([[16.1, 0.0, GROUND_Z + 2.75]], [[4.2, 1.8, 1.5]], [0.0])
    ev = evidence(cast([]), lifted)
    assert ev.terms["ground_gap"][0] == pytest.approx(2.0, abs=0.1)


def test_expected_returns_follow_the_beam_geometry():
    """Twice the range: about half the rings and half the columns cross the box."""
    near = Boxes([[15.0, 0.0, GROUND_Z + 0.75]], [[4.0, 1.8, 1.5]], [np.pi / 2])  # broadside
    far = Boxes([[30.0, 0.0, GROUND_Z + 0.75]], [[4.0, 1.8, 1.5]], [np.pi / 2])
    e_near, e_far = evidence(np.zeros((1, 3), np.float32), near), evidence(np.zeros((1, 3), np.float32), far)
    assert 2.5 < e_near.expected[0] / e_far.expected[0] < 6.0
    coarse = evidence(np.zeros((1, 3), np.float32), near, SENSOR_PRESETS["hdl32"])
    assert coarse.expected[0] < e_near.expected[0] / 2


def test_nan_points_and_no_boxes():
    scan = cast([(CAR_LO, CAR_HI)])
    scan[::7] = np.nan
    ev = evidence(scan, BOX)
    assert np.isfinite(ev.terms["density"]).all() and ev.n_in[0] > 50
    assert len(evidence(scan, Boxes.empty()).n_in) == 0


def test_a_second_thread_measures_the_same_evidence():
    scan = cast([(CAR_LO, CAR_HI), ((25.0, 3.0, GROUND_Z + 0.3), (29.0, 4.8, GROUND_Z + 1.4))])
    boxes = Boxes([[16.1, 0.0, GROUND_Z + 0.75], [27.0, 3.9, GROUND_Z + 0.8], [22.0, -6.0, GROUND_Z + 0.7]],
                  [[4.2, 1.8, 1.5], [4.0, 1.8, 1.6], [4.4, 1.9, 1.4]], [0.0, 0.3, -1.2], ["Car"] * 3, [0.3] * 3)
    one, two = evidence(scan, boxes).as_dict(), evidence(scan, boxes, workers=2).as_dict()
    assert one.keys() == two.keys()
    for key in one:
        np.testing.assert_array_equal(one[key], two[key])
    assert np.isfinite(one["ground_z"]).all() and (one["n_in"][:2] > 20).all()


def test_probability_combines_terms_with_the_configured_weights():
    config = FilterConfig(w_bias=-1.0, w_density=-1.0, w_free_space=0.5, w_ground_gap=2.0, w_score=-0.5)
    terms = {"density": np.array([0.0, -3.0]), "free_space": np.array([-5.0, 4.0]),
             "ground_gap": np.array([0.0, 0.0]), "score": np.array([2.0, 0.0]), "mismatch": np.array([np.nan, 0.2])}
    z = np.array([-1.0 + 0.0 - 2.5 + 0 - 1.0, -1.0 + 3.0 + 2.0])
    assert false_probability(terms, config) == pytest.approx(1 / (1 + np.exp(-z)))
    assert score_logit(np.array([0.0]), "sigmoid")[0] == 0.0
    assert score_logit(np.array([0.5]), "identity")[0] == pytest.approx(0.0)
    with pytest.raises(ConfigError):
        FilterConfig(rule="vote")
    with pytest.raises(ConfigError):
        FilterConfig(reject_threshold=1.0)


def test_shipped_filter_rejects_the_empty_box_and_keeps_the_car():
    config = FilterConfig()  # the calibrated KITTI defaults
    for scan, false in ((cast([]), True), (cast([(CAR_LO, CAR_HI)]), False)):
        terms = filter_terms(scan, BOX, config)
        assert (false_probability(terms, config)[0] > config.reject_threshold) == false


def test_defaults_are_the_shipped_calibration():
    from pathlib import Path

    from pcc_ros.pipeline.config import read_parameters

    shipped = read_parameters(Path(__file__).resolve().parents[1] / "config" / "detection_filter.yaml")
    defaults = FilterConfig()
    for key in ("w_bias", "w_density", "w_free_space", "w_ground_gap", "w_score", "w_mismatch", "reject_threshold",
                "sensor", "rule"):
        assert shipped[key] == getattr(defaults, key), key


def test_node_publishes_scores_terms_markers_and_counts():
    """A filter node on a physically cast scene: a car and an empty box. The kept / rejected
    detections carry the probability and the terms as extra hypotheses; the detector's own
    hypothesis still decodes as the label and score; RViz text and /diagnostics counts."""
    from pcc_ros.msg.detections import boxes_from_detection_array, detection_array_from_boxes
    from pcc_ros.msg.pointcloud2 import create_cloud
    from pcc_ros.msg.typestore import get_typestore
    from pcc_ros.runtime.base import RELIABLE, SENSOR_DATA
    from pcc_ros.runtime.local import LocalGraph, LocalRuntime
    from pcc_ros.runtime.node import NodeCore

    scan = cast([(CAR_LO, CAR_HI)])
    boxes = Boxes([[16.1, 0.0, GROUND_Z + 0.75], [25.0, -8.0, GROUND_Z + 0.75]], [[4.2, 1.8, 1.5]] * 2,
                  [0.0, 0.3], ["Car", "Car"], [0.6, 0.6], ["car", "empty"])
    graph = LocalGraph(simulated=True)
    NodeCore(LocalRuntime(graph, "filter_node"), "filter_node", "filter", {"backend": "input"}, threaded=False)
    got: dict[str, list] = {"kept": [], "rejected": [], "markers": [], "diag": []}
    probe = LocalRuntime(graph, "probe")
    dets_t = "vision_msgs/msg/Detection3DArray"
    probe.create_subscription("/detections_filtered", dets_t, got["kept"].append, RELIABLE)
    probe.create_subscription("/detections_rejected", dets_t, got["rejected"].append, RELIABLE)
    probe.create_subscription("/filter_markers", "visualization_msgs/msg/MarkerArray", got["markers"].append, RELIABLE)
    probe.create_subscription("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray", got["diag"].append, RELIABLE)
    driver = LocalRuntime(graph, "driver")
    driver.create_publisher("/points", "sensor_msgs/msg/PointCloud2", SENSOR_DATA).publish(
        create_cloud(scan, ["x", "y", "z"], "velodyne", 1_000_000_000))
    driver.create_publisher("/detections", dets_t, RELIABLE).publish(
        detection_array_from_boxes(boxes, "velodyne", 1_000_000_000))
    graph.advance_to(1_500_000_000)
    kept, rejected = got["kept"][0].detections, got["rejected"][0].detections
    assert [d.id for d in kept] == ["car"] and [d.id for d in rejected] == ["empty"]
    for det, false in ((kept[0], False), (rejected[0], True)):
        ids = [r.hypothesis.class_id for r in det.results]
        assert ids[0] == "Car" and ids[1] == "pcc_filter_score"
        assert {"pcc_filter/density", "pcc_filter/free_space", "pcc_filter/ground_gap", "pcc_filter/score"} <= set(ids)
        p = det.results[1].hypothesis.score
        assert (p > FilterConfig().reject_threshold) == false
    decoded = boxes_from_detection_array(got["kept"][0])
    assert decoded.label.tolist() == ["Car"] and decoded.score.tolist() == [0.6]  # filter hypotheses skipped
    get_typestore().serialize_cdr(got["kept"][0], dets_t)  # valid on the wire
    texts = [m.text for m in got["markers"][0].markers if m.text]
    assert any("p_false" in t and "kept" in t for t in texts) and any("rejected" in t for t in texts)
    values = {kv.key: kv.value for kv in got["diag"][-1].status[0].values}
    assert values["detections_kept"] == "1" and values["detections_rejected"] == "1"


def test_ray_index_on_the_boxes_sectors_equals_the_whole_scan(monkeypatch):
    """The ray index keeps only the points of the boxes' azimuth sectors (when these cover
    little of the circle): the same pairs, in the same order, as indexing the whole scan,
    across the +-pi seam and with NaN points."""
    import pcc_ros.pipeline.filter as filt

    rng = np.random.default_rng(3)
    scan = rng.uniform(-40.0, 40.0, (20_000, 3)).astype(np.float32)
    scan[:, 2] = rng.uniform(-2.0, 1.0, len(scan))
    scan[::97] = np.nan
    boxes = Boxes([[-20.0, 0.3, -1.0], [-18.0, -0.4, -0.9], [10.0, 12.0, -1.0], [5.0, -30.0, -0.8]],
                  [[4.2, 1.8, 1.5], [4.0, 1.8, 1.6], [4.4, 1.9, 1.4], [4.5, 1.8, 1.5]],
                  [0.2, -1.0, 2.5, 0.7], ["Car"] * 4, [0.5] * 4)
    x, y, z = (np.ascontiguousarray(scan[:, k]) for k in range(3))
    window = filt._angular_window(boxes)
    results = []
    for share in (0.0, 2.0):  # never / always on the sectors' subset
        monkeypatch.setattr(filt, "_SUBSET_SHARE", share)
        results.append((filt._rays_towards(x, y, z, *window), evidence(scan, boxes).as_dict()))
    (pairs_all, ev_all), (pairs_sub, ev_sub) = results
    assert len(pairs_all[0]) > 100
    for a, b in zip(pairs_all, pairs_sub):
        np.testing.assert_array_equal(a, b)
    for key in ev_all:
        np.testing.assert_array_equal(ev_all[key], ev_sub[key])
