"""The filter's ``corner`` term (pcc_ros.pipeline.evidence_profile): the share of a box's
mid-height returns in its four vertical corner columns. On ray-cast scenes a car body reads
more than a vegetation blob (an ellipsoid: its corners are air) or a thin wall in the same box;
an empty box reads the prior (a car's value); non-finite points count nowhere; the compiled
pass agrees with a plain numpy count on random scans and boxes."""

from __future__ import annotations

import numpy as np
import pytest
from scan_scenes import GROUND_Z, SENSOR, cast

from pcc_ros.geometry.canonical import to_box_local
from pcc_ros.pipeline.evidence import EVIDENCE_GROUND
from pcc_ros.pipeline.evidence_profile import (
    CORNER_COLUMNS,
    CORNER_PRIOR,
    CORNER_PRIOR_RETURNS,
    FACE_MARGIN,
    profile_terms,
)
from pcc_ros.pipeline.filter import FilterConfig, filter_terms
from pcc_ros.types import Boxes

#: a car-sized box seen obliquely (its near end and its right side face the sensor)
CENTRE = np.array([14.0, 4.0, GROUND_Z + 0.75])
HALF = np.array([2.1, 0.9, 0.75])
BOX = Boxes([CENTRE], [2 * HALF], [0.0], ["Car"], [0.5])


def corner_of(scan: np.ndarray, boxes: Boxes = BOX) -> dict[str, np.ndarray]:
    return profile_terms(scan, boxes, SENSOR, measure={"corner"})


def test_a_car_body_fills_its_corners_a_blob_and_a_wall_do_not():
    body = (CENTRE - HALF + [0, 0, 0.3], CENTRE + HALF)  # the body fills the box over its wheels
    blob = (CENTRE + np.array([0, 0, -0.15]), HALF * [1.0, 1.0, 0.8])  # an ellipsoid inscribed in the box
    wall = (CENTRE - np.array([2.1, 0.15, 0.75]), CENTRE + np.array([2.1, 0.15, 0.45]))  # a thin slab along the box
    car, bush, slab = (corner_of(s)["corner"][0] for s in (cast([body]), cast(ellipsoids=[blob]), cast([wall])))
    assert car > 0.5  # the near end and the right side: a large part of each in the corner columns
    assert car > bush + 0.15 and car > slab + 0.2
    # a wall along the box's axis holds none of its returns in the corners: the prior alone
    corner, mid = _reference(cast([wall]), BOX)
    assert corner[0] == 0 and mid[0] > 30
    assert slab == pytest.approx(CORNER_PRIOR * CORNER_PRIOR_RETURNS / (mid[0] + CORNER_PRIOR_RETURNS))


def test_an_empty_box_reads_a_cars_value_and_nan_points_count_nowhere():
    empty = corner_of(cast())
    assert empty["corner"][0] == pytest.approx(CORNER_PRIOR)
    scan = cast(((CENTRE - HALF + [0, 0, 0.3], CENTRE + HALF),))
    noisy = np.concatenate([scan, np.full((50, 3), np.nan), [[np.nan, 14.0, GROUND_Z + 0.5]] * 5,
                            [[14.0, np.inf, GROUND_Z + 0.5]]])
    assert corner_of(noisy)["corner"][0] == corner_of(scan)["corner"][0]
    assert np.isfinite(corner_of(np.zeros((0, 3)))["corner"]).all()


def _reference(points: np.ndarray, boxes: Boxes) -> tuple[np.ndarray, np.ndarray]:
    """Per box: (corner returns, mid-height body returns), a plain numpy count."""
    corner, mid = np.zeros(len(boxes)), np.zeros(len(boxes))
    length, width, top = CORNER_COLUMNS
    for b in range(len(boxes)):
        (cx, cy, cz), half = boxes.center[b], boxes.size[b] / 2
        x, y, z = to_box_local(points[:, 0], points[:, 1], points[:, 2], cx, cy, cz,
                               np.cos(boxes.yaw[b]), np.sin(boxes.yaw[b]))
        body = (np.abs(x) <= half[0] + FACE_MARGIN) & (np.abs(y) <= half[1] + FACE_MARGIN)
        body &= (z >= -half[2] + EVIDENCE_GROUND) & (z <= half[2] * (2 * top - 1))
        mid[b] = body.sum()
        corner[b] = (body & (np.abs(x) >= half[0] * (1 - 2 * length)) & (np.abs(y) >= half[1] * (1 - 2 * width))).sum()
    return corner, mid


def test_the_compiled_pass_counts_as_numpy_does():
    rng = np.random.default_rng(3)
    points = np.c_[rng.uniform(-20, 20, (60_000, 2)), rng.uniform(-2, 1, 60_000)]
    boxes = Boxes(np.c_[rng.uniform(-15, 15, (12, 2)), rng.uniform(-1.5, 0, 12)],
                  np.c_[rng.uniform(3, 5, 12), rng.uniform(1.5, 2.2, 12), rng.uniform(1.3, 2, 12)],
                  rng.uniform(-np.pi, np.pi, 12))
    corner, mid = _reference(points, boxes)
    assert mid.min() > 20  # every box holds returns
    want = (corner + CORNER_PRIOR * CORNER_PRIOR_RETURNS) / (mid + CORNER_PRIOR_RETURNS)
    np.testing.assert_allclose(corner_of(points, boxes)["corner"], want, rtol=1e-12)
    # float32 scans (sensor data): the same counts but at rounding boundaries
    got32 = corner_of(points.astype(np.float32), boxes)["corner"]
    np.testing.assert_allclose(got32, want, atol=0.02)


def test_corner_is_measured_only_where_weighted():
    scan = cast(((CENTRE - HALF + [0, 0, 0.3], CENTRE + HALF),))
    unweighted = FilterConfig(w_corner=0.0, trees="")
    assert "corner" not in filter_terms(scan, BOX, unweighted, sensor=SENSOR, weighted_only=True)
    weighted = filter_terms(scan, BOX, FilterConfig(w_corner=-5.0, trees=""), sensor=SENSOR, weighted_only=True)
    every = filter_terms(scan, BOX, FilterConfig(w_corner=0.0, trees=""), sensor=SENSOR)
    assert weighted["corner"][0] == every["corner"][0] > 0.5
