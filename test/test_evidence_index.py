"""The BEV index of the scan that the local ground and the profile pass share
(``pipeline/evidence_index``): each box's cell runs hold every point its exact test accepts, and
the profile terms measured over the ground's index (the pipeline's call, either thread setting)
are bit for bit those of the profile pass alone and of 24858c5's numpy pass (pair arrays in point
order, ``benchmarks/_reference_profile``), although the index hands the points over cell by cell."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks._reference_profile import profile_terms as reference_profile
from pcc_ros.geometry.beams import SENSOR_PRESETS
from pcc_ros.geometry.boxes import points_in_boxes
from pcc_ros.pipeline.evidence import evidence
from pcc_ros.pipeline.evidence_index import Footprints, bev_index
from pcc_ros.pipeline.evidence_profile import PROFILE_TERMS, profile_terms
from pcc_ros.scratch import Scratch
from pcc_ros.types import Boxes


def _scene(rng: np.random.Generator, n_boxes: int, spread: float, dtype) -> tuple[np.ndarray, Boxes]:
    """Car-sized yawed boxes on the ground around the sensor, returns on and around them, a
    scattered background and a few NaN rows."""
    centre = np.c_[rng.uniform(-spread, spread, (n_boxes, 2)), rng.uniform(-1.2, -0.6, n_boxes)]
    centre[np.hypot(centre[:, 0], centre[:, 1]) < 6, 0] += 8.0  # the sensor outside every box
    size = np.c_[rng.uniform(3.5, 5.0, n_boxes), rng.uniform(1.6, 2.0, n_boxes), rng.uniform(1.4, 1.8, n_boxes)]
    boxes = Boxes(centre, size, rng.uniform(-np.pi, np.pi, n_boxes), ["Car"] * n_boxes, rng.uniform(0, 1, n_boxes))
    local = rng.uniform(-0.7, 0.7, (n_boxes, 150, 3)) * size[:, None, :]  # in, on and around each box
    c, s = np.cos(boxes.yaw)[:, None], np.sin(boxes.yaw)[:, None]
    near = np.stack([centre[:, None, 0] + c * local[..., 0] - s * local[..., 1],
                     centre[:, None, 1] + s * local[..., 0] + c * local[..., 1],
                     centre[:, None, 2] + local[..., 2]], axis=-1).reshape(-1, 3)
    background = np.c_[rng.uniform(-spread - 5, spread + 5, (3000, 2)), rng.uniform(-2.5, 2.0, 3000)]
    scan = np.concatenate([near, background, np.full((3, 3), np.nan)])
    return scan[rng.permutation(len(scan))].astype(dtype), boxes


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("spread", [25.0, 4000.0])  # 4 km: the grid's cells coarsen
def test_cell_runs_hold_every_point_inside(dtype, spread):
    scan, boxes = _scene(np.random.default_rng(3), 30, spread, dtype)
    half = boxes.size / 2
    cos, sin = np.cos(boxes.yaw), np.sin(boxes.yaw)
    footprints = Footprints(boxes.center[:, 0], boxes.center[:, 1], cos, sin, half[:, 0], half[:, 1], -10.0, 10.0)
    x, y, z = (np.ascontiguousarray(scan[:, k]) for k in range(3))
    index = bev_index(x, y, z, [footprints], Scratch())
    first, last, ends = index.runs[0]
    begin = 0
    for b, inside in enumerate(points_in_boxes(scan, boxes)):
        candidates = np.concatenate([index.order[index.start[f]:index.start[e + 1]]
                                     for f, e in zip(first[begin:ends[b]], last[begin:ends[b]])] or [[]])
        begin = ends[b]
        assert len(inside) and np.isin(inside, candidates).all(), b
        assert np.isfinite(scan[candidates.astype(np.int64)]).all()  # NaN rows are never placed


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_profile_over_the_grounds_index_is_the_pass_alone_and_24858c5s(dtype):
    scan, boxes = _scene(np.random.default_rng(4), 25, 25.0, dtype)
    sensor = SENSOR_PRESETS["hdl64"]
    alone = profile_terms(scan, boxes, sensor)
    reference = reference_profile(scan, boxes, sensor)
    assert (alone["n_body"] > 20).sum() > 10  # depth sums of many returns: their order shows
    for key in reference:
        np.testing.assert_array_equal(alone[key], reference[key], err_msg=key)
    for workers in (1, 2):
        shared = evidence(scan, boxes, sensor, workers=workers, profile=PROFILE_TERMS).profile
        assert set(shared) == set(alone)
        for key in alone:
            np.testing.assert_array_equal(shared[key], alone[key], err_msg=key)
