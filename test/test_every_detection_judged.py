"""No detection of a filtered class leaves the filter without a score or the documented
``pcc_filter_unjudged`` marker, at any number of boxes per frame: ``max_instances`` bounds the
completion network only, a missing shape term is marginalised, and boxes that fail the checks
(NaN) are republished marked and counted on /diagnostics."""

from __future__ import annotations

import copy

import numpy as np

from pcc_ros.msg.detections import detection_array_from_boxes
from pcc_ros.msg.pointcloud2 import create_cloud
from pcc_ros.pipeline.filter import (
    SCORE_CLASS_ID,
    TERMS,
    UNJUDGED_CLASS_ID,
    FilterConfig,
    false_probability,
    term_matrix,
    without_evidence,
)
from pcc_ros.runtime.base import RELIABLE, SENSOR_DATA
from pcc_ros.runtime.local import LocalGraph, LocalRuntime
from pcc_ros.runtime.node import NodeCore
from pcc_ros.types import Boxes

CLOUD, DETS = "sensor_msgs/msg/PointCloud2", "vision_msgs/msg/Detection3DArray"
STAMP = 1_000_000_000


def _street(n_cars: int, n_people: int, seed: int = 0):
    """A ground scan with car-sized clusters in half the boxes; ``n_cars`` Car and ``n_people``
    Pedestrian boxes on a grid around the sensor."""
    rng = np.random.default_rng(seed)
    radius = rng.uniform(4.0, 70.0, 30_000)
    angle = rng.uniform(-np.pi, np.pi, 30_000)
    ground = np.c_[radius * np.cos(angle), radius * np.sin(angle), np.full(30_000, -1.73)]
    k = np.arange(n_cars + n_people)
    ring, slot = k // 40, k % 40
    r = 8.0 + 4.0 * ring
    a = slot * (2 * np.pi / 40) + ring * 0.05
    centre = np.c_[r * np.cos(a), r * np.sin(a), np.full(len(k), -0.98)]
    size = np.tile([4.2, 1.8, 1.5], (len(k), 1))
    size[n_cars:] = [0.6, 0.6, 1.7]
    cars = [centre[i] + rng.uniform(-1, 1, (60, 3)) * [2.0, 0.85, 0.7] for i in range(0, n_cars, 2)]
    points = np.concatenate([ground, *cars]).astype(np.float32)
    labels = ["Car"] * n_cars + ["Pedestrian"] * n_people
    boxes = Boxes(centre, size, a + np.pi / 2, labels, rng.uniform(0.3, 0.95, len(k)), [str(i) for i in k])
    return points, boxes


def test_three_hundred_boxes_every_car_scored_or_marked_and_counted():
    graph = LocalGraph(simulated=True)
    core = NodeCore(LocalRuntime(graph, "detection_filter_node"), "detection_filter_node", "filter",
                    {"backend": "mirror"}, threaded=False)  # max_instances: 32 (the default)
    assert core.pipeline.config.max_instances < 300
    got = {t: [] for t in ("/detections_filtered", "/detections_rejected")}
    probe = LocalRuntime(graph, "probe")
    for topic, sink in got.items():
        probe.create_subscription(topic, DETS, sink.append, RELIABLE)
    points, boxes = _street(300, 5)
    dets = detection_array_from_boxes(boxes, "velodyne", STAMP)
    broken = copy.deepcopy(dets.detections[0])
    broken.bbox.center.position.x = float("nan")  # cannot be judged at all
    dets.detections.append(broken)
    driver = LocalRuntime(graph, "driver")
    driver.create_publisher("/points", CLOUD, SENSOR_DATA).publish(create_cloud(points, ["x", "y", "z"], "velodyne",
                                                                                STAMP))
    driver.create_publisher("/detections", DETS, RELIABLE).publish(dets)
    assert core.frames == 1
    out = [d for topic in got for array in got[topic] for d in array.detections]
    assert len(out) == 306  # nothing dropped, the NaN box included
    classes = [[h.hypothesis.class_id for h in d.results] for d in out]
    cars = [c for c in classes if c[0] == "Car"]
    scored = sum(SCORE_CLASS_ID in c for c in cars)
    marked = sum(UNJUDGED_CLASS_ID in c for c in cars)
    assert scored == 300 and marked == 1 and len(cars) == 301
    assert not any(SCORE_CLASS_ID in c or UNJUDGED_CLASS_ID in c for c in classes if c[0] == "Pedestrian")
    broken_out = [d for d in got["/detections_filtered"][0].detections if UNJUDGED_CLASS_ID in
                  [h.hypothesis.class_id for h in d.results]]
    assert len(broken_out) == 1 and np.isnan(broken_out[0].bbox.center.position.x)  # published, as received
    values = core.diagnostics_values()
    assert values["detections_unjudged"] == "1" and values["last_frame_unjudged"] == "1"
    assert int(values["detections_kept"]) + int(values["detections_rejected"]) == 300
    assert values["skipped_over_max_instances"] == str(300 - 32)  # not completed, judged all the same
    # judged on the evidence: the boxes holding a car-sized cluster read less false than the empty ones
    p_false = {d.id: h.hypothesis.score for d in out for h in d.results if h.hypothesis.class_id == SCORE_CLASS_ID}
    full = [p_false[str(i)] for i in range(0, 300, 2)]
    empty = [p_false[str(i)] for i in range(1, 300, 2)]
    assert np.median(full) < np.median(empty)


def test_a_missing_shape_term_is_marginalised_to_its_calibration_mean():
    terms = {"density": np.zeros(2), "free_space": np.zeros(2), "ground_gap": np.zeros(2), "score": np.zeros(2),
             "mismatch": np.array([0.8, np.nan])}
    np.testing.assert_array_equal(term_matrix(terms, 0.4)[:, TERMS.index("mismatch")], [0.8, 0.4])
    config = FilterConfig(w_mismatch=2.0, mismatch_mean=0.4, w_bias=0.0)
    missing = false_probability({**terms, "mismatch": np.array([np.nan, 0.4])}, config)
    assert missing[0] == missing[1] == 1.0 / (1.0 + np.exp(-0.8))


def _shadowed_street(seed: int = 0):
    """A wall 10 m ahead (x = 10, |y| <= 2.5 m, up to 1.2 m high) hides two boxes 20 m ahead
    behind it: an empty one and a car whose returns the wall stops (none reach it). A third,
    empty box stands in the open at the same range 30 deg aside, the ground and a far wall
    behind it returning the rays that cross it. Ground everywhere outside the wall's shadow."""
    rng = np.random.default_rng(seed)
    wy, wz = np.meshgrid(np.arange(-2.5, 2.5, 0.04), np.arange(-1.73, 1.2, 0.04))
    wall = np.c_[np.full(wy.size, 10.0), wy.ravel(), wz.ravel()]
    radius, angle = rng.uniform(3.0, 60.0, 60_000), rng.uniform(-np.pi, np.pi, 60_000)
    ground = np.c_[radius * np.cos(angle), radius * np.sin(angle), np.full(60_000, -1.73)]
    hidden = (ground[:, 0] > 10.0) & (np.abs(ground[:, 1]) < 2.5 * ground[:, 0] / 10.0)
    far = 45.0 * np.array([np.cos(np.pi / 6), np.sin(np.pi / 6)])
    fy, fz = np.meshgrid(np.arange(-6.0, 6.0, 0.05), np.arange(-1.73, 2.0, 0.05))
    back = np.c_[far[0] - 0.5 * fy.ravel(), far[1] + np.sqrt(0.75) * fy.ravel(), fz.ravel()]
    points = np.concatenate([wall, ground[~hidden], back]).astype(np.float32)
    open_centre = 20.0 * np.array([np.cos(np.pi / 6), np.sin(np.pi / 6)])
    boxes = Boxes([[20.0, -1.0, -0.98], [20.0, 1.0, -0.98], [*open_centre, -0.98]], np.tile([4.2, 1.8, 1.5], (3, 1)),
                  [0.0, 0.0, np.pi / 6], ["Car"] * 3, [0.9, 0.6, 0.5], ["empty", "car", "open"])
    return points, boxes


def test_a_box_the_scan_says_nothing_about_is_unjudged_marked_and_counted():
    graph = LocalGraph(simulated=True)
    core = NodeCore(LocalRuntime(graph, "detection_filter_node"), "detection_filter_node", "filter",
                    {"backend": "input"}, threaded=False)
    got: list = []
    LocalRuntime(graph, "probe").create_subscription("/detections_filtered", DETS, got.append, RELIABLE)
    points, boxes = _shadowed_street()
    driver = LocalRuntime(graph, "driver")
    driver.create_publisher("/points", CLOUD, SENSOR_DATA).publish(create_cloud(points, ["x", "y", "z"], "velodyne",
                                                                                STAMP))
    driver.create_publisher("/detections", DETS, RELIABLE).publish(detection_array_from_boxes(boxes, "velodyne",
                                                                                              STAMP))
    assert core.frames == 1
    hyps = {d.id: {h.hypothesis.class_id: h.hypothesis.score for h in d.results}
            for a in got for d in a.detections}
    for hidden in ("empty", "car"):  # kept, marked, no p_false: the scan holds nothing on them
        assert UNJUDGED_CLASS_ID in hyps[hidden] and SCORE_CLASS_ID not in hyps[hidden]
    result = core.pipeline.process(points, boxes)
    assert list(result.status[:2]) == ["unjudged", "unjudged"]
    assert result.filter_terms["n_pass"][2] > 0 and result.status[2] in ("kept", "rejected")  # rays cross it: judged
    assert np.isnan(result.filter_score[:2]).all() and np.isfinite(result.filter_score[2])
    values = core.diagnostics_values()
    assert values["skipped_unjudged_no_evidence"] == "2" and values["detections_unjudged"] == "2"
    status = core.diagnostics_message().status[0]
    assert "could not be judged" not in status.message  # counted, not a warning: no work was lost


def test_without_evidence_needs_no_return_no_core_ray_and_no_overlap():
    zero = np.zeros(4)
    terms = {"n_in": np.array([0.0, 1.0, 0.0, 0.0]), "n_pass": np.array([0.0, 0.0, 2.0, 0.0]), "n_stop": zero,
             "overlap": np.array([0.0, 0.0, 0.0, 0.4])}
    np.testing.assert_array_equal(without_evidence(terms), [True, False, False, False])
    assert not without_evidence({**terms, "n_in": np.full(4, np.nan)}).any()  # rays not measured: judged
