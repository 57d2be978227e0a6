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
    # the threshold the decisions used (no sensor_thresholds: reject_threshold) and the preset matched
    assert values["reject_threshold_in_force"] == f"{core.pipeline.config.filter.reject_threshold:.4f}"
    assert values["sensor_preset_matched"] == (core.pipeline.beam_model.preset or "-")
    height = core.pipeline.beam_model.mount_height
    assert values["sensor_height_m"] == ("-" if height is None else f"{height:.2f}")
    # judged on the evidence: the boxes holding a car-sized cluster read less false than the empty ones
    p_false = {d.id: h.hypothesis.score for d in out for h in d.results if h.hypothesis.class_id == SCORE_CLASS_ID}
    full = [p_false[str(i)] for i in range(0, 300, 2)]
    empty = [p_false[str(i)] for i in range(1, 300, 2)]
    assert np.median(full) < np.median(empty)


def test_a_missing_shape_term_is_marginalised_to_its_calibration_mean():
    terms = {"density": np.zeros(2), "free_space": np.zeros(2), "ground_gap": np.zeros(2), "score": np.zeros(2),
             "mismatch": np.array([0.8, np.nan])}
    np.testing.assert_array_equal(term_matrix(terms, 0.4)[:, TERMS.index("mismatch")], [0.8, 0.4])
    config = FilterConfig(w_mismatch=2.0, mismatch_mean=0.4, w_bias=0.0, trees="")
    missing = false_probability({**terms, "mismatch": np.array([np.nan, 0.4])}, config)
    assert missing[0] == missing[1] == 1.0 / (1.0 + np.exp(-0.8))
