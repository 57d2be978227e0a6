"""Box corners, points-in-boxes against a slow reference, crops, rotated IoU."""

from __future__ import annotations

import numpy as np
import pytest

from pcc_ros.errors import DataError
from pcc_ros.geometry.boxes import (
    BoxCandidates,
    box_corners,
    canonical_crops,
    circles_meet,
    crop_canonical,
    iou_3d,
    iou_bev,
    iou_bev_pairs,
    pairs_in_boxes,
    points_in_boxes,
    polygon_intersection_area,
)
from pcc_ros.geometry.canonical import from_canonical, to_canonical
from pcc_ros.types import Boxes


def slow_points_in_boxes(points, boxes, margin=0.0, ground_margin=0.0):
    """Reference: one float64 full-scan test per box."""
    out = []
    for i in range(len(boxes)):
        d = points[:, :3].astype(np.float64) - boxes.center[i]
        c, s = np.cos(boxes.yaw[i]), np.sin(boxes.yaw[i])
        lx, ly = c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]
        h = boxes.size[i] / 2
        m = (np.abs(lx) <= h[0] + margin) & (np.abs(ly) <= h[1] + margin)
        m &= (d[:, 2] <= h[2] + margin) & (d[:, 2] >= -h[2] - margin + ground_margin)
        out.append(np.flatnonzero(m))
    return out


def random_scene(rng, n_points=20000, n_boxes=25, dtype=np.float32):
    points = rng.uniform([-20, -20, -2], [20, 20, 2], (n_points, 3)).astype(dtype)
    # Cluster some boxes so they overlap, the rest anywhere; all rotated.
    centre = rng.uniform(-15, 15, (n_boxes, 3))
    centre[: n_boxes // 3] = centre[0] + rng.normal(0, 1.0, (n_boxes // 3, 3))
    size = np.c_[rng.uniform(0.5, 6, n_boxes), rng.uniform(0.5, 3, n_boxes), rng.uniform(0.5, 3, n_boxes)]
    boxes = Boxes(centre, size, rng.uniform(-np.pi, np.pi, n_boxes))
    # Put points in every box so no crop is trivially empty.
    inside = rng.uniform(-0.5, 0.5, (n_boxes, 40, 3)) * size[:, None, :]
    extra = np.concatenate([from_canonical(p / s[0], c, y, s[0]) for p, c, y, s in
                            zip(inside, boxes.center, boxes.yaw, boxes.size)])
    return np.concatenate([points, extra.astype(dtype)]), boxes


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_points_in_boxes_matches_slow_reference(seed, dtype):
    rng = np.random.default_rng(seed)
    points, boxes = random_scene(rng, dtype=dtype)
    for margin, ground in [(0.0, 0.0), (0.2, 0.0), (0.1, 0.3)]:
        fast = points_in_boxes(points, boxes, margin=margin, ground_margin=ground)
        slow = slow_points_in_boxes(points, boxes, margin, ground)
        assert len(fast) == len(boxes)
        for f, s in zip(fast, slow):
            np.testing.assert_array_equal(f, s)  # same indices, ascending


def test_overlapping_boxes_share_points_and_cell_size_does_not_matter():
    rng = np.random.default_rng(5)
    points = rng.uniform(-3, 3, (5000, 3)).astype(np.float32)
    boxes = Boxes([[0, 0, 0], [0.5, 0.2, 0.1], [0, 0, 0]], [[4, 2, 2], [3, 2, 2], [1, 1, 1]], [0.3, -0.7, 1.2])
    ref = slow_points_in_boxes(points, boxes)
    assert len(np.intersect1d(ref[0], ref[1])) > 100  # genuinely overlapping
    for cell in (0.1, 0.7, 5.0):
        for f, s in zip(points_in_boxes(points, boxes, cell=cell), ref):
            np.testing.assert_array_equal(f, s)


@pytest.mark.parametrize("stack", [2, 5, 12, 70])  # a few boxes per cell, more, and over 64 (the CSR walk)
def test_stacked_boxes_each_get_their_points(stack):
    rng = np.random.default_rng(stack)
    points = rng.uniform(-4, 4, (4000, 3)).astype(np.float32)
    boxes = Boxes(rng.normal(0, 0.3, (stack, 3)), rng.uniform(1.0, 4.0, (stack, 3)), rng.uniform(-np.pi, np.pi, stack))
    for f, s in zip(points_in_boxes(points, boxes, margin=0.1), slow_points_in_boxes(points, boxes, 0.1)):
        np.testing.assert_array_equal(f, s)


def test_margin_reaches_the_corners_of_a_yawed_box():
    # The margin-enlarged box of a 45-degree box reaches margin * sqrt(2) beyond the extent
    # of its corners: points there (the enlarged corners, every side) are inside it.
    box = Boxes([[10.0, -3.0, 0.0]], [[4.0, 2.0, 2.0]], [np.pi / 4])
    local = np.array([[2.48, 1.48, 0.0], [-2.48, 1.48, 0.0], [-2.48, -1.48, 0.0], [2.48, -1.48, 0.0]])
    points = from_canonical(local / 4.0, box.center[0], box.yaw[0], 4.0).astype(np.float32)
    for cell in (None, 0.1, 0.45, 3.0):
        np.testing.assert_array_equal(points_in_boxes(points, box, margin=0.5, cell=cell)[0], [0, 1, 2, 3])
        assert len(points_in_boxes(points, box, margin=0.45, cell=cell)[0]) == 0


def test_pairs_in_boxes_are_the_split_pairs():
    rng = np.random.default_rng(4)
    points, boxes = random_scene(rng, n_points=3000)
    point, box = pairs_in_boxes(points, boxes, margin=0.1, ground_margin=0.05)
    assert (np.diff(box) >= 0).all()  # grouped by box, boxes ascending
    expected = slow_points_in_boxes(points, boxes, 0.1, 0.05)
    np.testing.assert_array_equal(point, np.concatenate(expected))  # points ascending within a box
    np.testing.assert_array_equal(box, np.repeat(np.arange(len(boxes)), [len(e) for e in expected]))


def test_ground_margin_removes_ground_returns():
    rng = np.random.default_rng(3)
    ground = np.c_[rng.uniform(-2, 2, 500), rng.uniform(-0.8, 0.8, 500), np.full(500, -0.75)].astype(np.float32)
    body = rng.uniform([-2, -0.8, -0.5], [2, 0.8, 0.75], (500, 3)).astype(np.float32)
    boxes = Boxes([[0, 0, 0]], [[4.2, 1.8, 1.5]], [0.0])
    idx_all = points_in_boxes(np.r_[ground, body], boxes)[0]
    idx_cut = points_in_boxes(np.r_[ground, body], boxes, ground_margin=0.2)[0]
    assert np.isin(np.arange(500), idx_all).all()
    assert not np.isin(np.arange(500), idx_cut).any()
    assert len(idx_cut) > 400


def test_nan_points_and_bad_boxes():
    points = np.array([[0, 0, 0], [np.nan, 0, 0], [0.1, np.nan, 0]], dtype=np.float32)
    boxes = Boxes([[0, 0, 0]], [[1, 1, 1]], [0.0])
    np.testing.assert_array_equal(points_in_boxes(points, boxes)[0], [0])
    with pytest.raises(DataError, match="box 0"):
        points_in_boxes(points, Boxes([[np.nan, 0, 0]], [[1, 1, 1]], [0.0]))
    with pytest.raises(DataError, match="shape"):
        points_in_boxes(np.zeros((4, 2)), boxes)
    assert points_in_boxes(points, Boxes.empty()) == []
    empty = points_in_boxes(np.zeros((0, 3), np.float32), boxes)
    assert len(empty) == 1 and len(empty[0]) == 0


def test_nan_inf_points_empty_scans_zero_and_far_boxes():
    rng = np.random.default_rng(8)
    points, boxes = random_scene(rng, n_points=4000)
    points[::7, 0] = np.nan  # NaN in each coordinate, and infinities
    points[1::7, 1] = np.nan
    points[2::7, 2] = np.nan
    points[3::11, 0] = np.inf
    points[4::11, 1] = -np.inf
    fast = points_in_boxes(points, boxes, margin=0.1)
    for f, s in zip(fast, slow_points_in_boxes(points, boxes, 0.1)):
        np.testing.assert_array_equal(f, s)
    assert sum(len(f) for f in fast) > 500
    all_nan = np.full((100, 3), np.nan, np.float32)
    assert all(len(i) == 0 for i in points_in_boxes(all_nan, boxes))
    assert BoxCandidates(all_nan, boxes).pairs_per_box.sum() == 0  # NaN is never a candidate
    # boxes far outside the scan: nothing inside, nothing estimated, nothing formed
    far = Boxes(boxes.center + np.array([5000.0, -3000.0, 0.0]), boxes.size, boxes.yaw)
    candidates = BoxCandidates(points, far, margin=1.0)
    assert candidates.pairs_per_box.sum() == 0
    indices, canon = canonical_crops(candidates)
    assert len(indices) == len(far) and all(len(i) == 0 and c.shape == (0, 3) for i, c in zip(indices, canon))
    # boxes kilometres apart (the grid coarsens to a million cells) with a scan around each
    apart = Boxes([[0, 0, 0], [3000.0, 2000.0, 0]], [[4, 2, 2], [4, 2, 2]], [0.3, -1.0])
    around = np.concatenate([rng.uniform(-3, 3, (2000, 3)), rng.uniform(-3, 3, (2000, 3)) + np.array([3000, 2000, 0])])
    around = around.astype(np.float32)
    for f, s in zip(points_in_boxes(around, apart, margin=0.2), slow_points_in_boxes(around, apart, 0.2)):
        np.testing.assert_array_equal(f, s)
        assert len(f) > 50
    # empty scan, zero boxes
    empty = np.zeros((0, 4), np.float32)
    indices, canon = crop_canonical(empty, boxes, margin=0.1)
    assert len(indices) == len(boxes) and all(len(i) == 0 and c.shape == (0, 3) for i, c in zip(indices, canon))
    assert crop_canonical(points, Boxes.empty()) == ([], [])
    point, box = pairs_in_boxes(points, Boxes.empty())
    assert len(point) == len(box) == 0
    assert BoxCandidates(empty, boxes).pairs_per_box.tolist() == [0] * len(boxes)
    with pytest.raises(DataError, match="shape"):
        BoxCandidates(np.zeros(5), boxes)


@pytest.mark.parametrize("stack", [1, 3, 12, 70])  # candidates expand by one box per cell, a padded table, a CSR walk
def test_candidate_bound_and_box_subsets(stack):
    rng = np.random.default_rng(20 + stack)
    points = rng.uniform([-30, -30, -2, 0], [30, 30, 2, 1], (30000, 4)).astype(np.float32)  # x, y, z, intensity
    centres = np.repeat(rng.uniform([-25, -25, -1], [25, 25, 1], (6, 3)), stack, axis=0)
    centres += rng.normal(0, 0.3, (6 * stack, 3))
    boxes = Boxes(centres, rng.uniform(1.0, 5.0, (6 * stack, 3)), rng.uniform(-np.pi, np.pi, 6 * stack))
    candidates = BoxCandidates(points, boxes, margin=0.1, ground_margin=0.2)
    slow = slow_points_in_boxes(points, boxes, 0.1, 0.2)
    real = np.array([len(s) for s in slow])
    assert (candidates.pairs_per_box >= real).all() and real.sum() > 100
    # the bound counts the points of the box's cells: within a small factor of its bounding rectangle's
    assert candidates.pairs_per_box.sum() < 4 * real.sum() + 1000
    for keep in (None, np.arange(len(boxes)) % 2 == 0, np.array([len(boxes) - 1]), np.zeros(len(boxes), bool)):
        indices, canon = canonical_crops(candidates, keep)
        chosen = np.zeros(len(boxes), bool)
        chosen[slice(None) if keep is None else keep] = True
        for b, (idx, c) in enumerate(zip(indices, canon)):
            np.testing.assert_array_equal(idx, slow[b] if chosen[b] else [])
            expected = to_canonical(points[idx], boxes.center[b], boxes.yaw[b], boxes.size[b, 0])
            np.testing.assert_allclose(c, expected, atol=1e-5)


@pytest.mark.parametrize("chunk", [1, 7, 1000])
def test_pairs_tested_in_chunks_give_the_same_crops(monkeypatch, chunk):
    import pcc_ros.geometry.boxes as boxes_module

    rng = np.random.default_rng(chunk)
    points, boxes = random_scene(rng, n_points=6000)
    expected = crop_canonical(points, boxes, 0.1, 0.05)
    monkeypatch.setattr(boxes_module, "_PAIR_CHUNK", chunk)  # chunk borders inside boxes, boxes inside chunks
    indices, canon = crop_canonical(points, boxes, 0.1, 0.05)
    slow = slow_points_in_boxes(points, boxes, 0.1, 0.05)
    for a, b, s in zip(indices, expected[0], slow):
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(a, s)
    for a, b in zip(canon, expected[1]):
        np.testing.assert_array_equal(a, b)


def test_float64_scans_and_threads_give_the_same_crops():
    from concurrent.futures import ThreadPoolExecutor

    rng = np.random.default_rng(12)
    big, boxes = random_scene(rng, n_points=40000)
    small = big[::13]
    expected = {n: crop_canonical(p, boxes, 0.1, 0.05) for n, p in (("big", big), ("small", small))}
    for f, s in zip(points_in_boxes(big.astype(np.float64), boxes, 0.1), slow_points_in_boxes(big, boxes, 0.1)):
        np.testing.assert_array_equal(f, s)
    # views that are not C-contiguous: the first columns of a wider scan, a Fortran-order copy
    wide = np.concatenate([big, rng.uniform(0, 1, (len(big), 2)).astype(np.float32)], axis=1)
    for view in (wide[:, :3], np.asfortranarray(big)):
        indices, canon = crop_canonical(view, boxes, 0.1, 0.05)
        for a, b in zip(indices, expected["big"][0]):
            np.testing.assert_array_equal(a, b)
        for a, b in zip(canon, expected["big"][1]):
            np.testing.assert_array_equal(a, b)
    # per-thread work arrays: scans of different sizes, alternately, on two threads
    with ThreadPoolExecutor(2) as pool:
        runs = list(pool.map(lambda n: (n, crop_canonical(big if n == "big" else small, boxes, 0.1, 0.05)),
                             ["big", "small"] * 6))
    for name, (indices, canon) in runs:
        for a, b in zip(indices, expected[name][0]):
            np.testing.assert_array_equal(a, b)
        for a, b in zip(canon, expected[name][1]):
            np.testing.assert_array_equal(a, b)


def test_crop_canonical_matches_to_canonical():
    rng = np.random.default_rng(7)
    points, boxes = random_scene(rng)
    indices, canon = crop_canonical(points, boxes, margin=0.05)
    for i, (idx, c) in enumerate(zip(indices, canon)):
        assert c.dtype == np.float32 and c.shape == (len(idx), 3)
        expected = to_canonical(points[idx], boxes.center[i], boxes.yaw[i], boxes.size[i, 0])
        np.testing.assert_allclose(c, expected, atol=1e-5)


def test_canonical_round_trip():
    rng = np.random.default_rng(11)
    p = rng.normal(0, 20, (1000, 3))
    c = to_canonical(p, [3.0, -4.0, 0.5], 2.1, 4.3)
    np.testing.assert_allclose(from_canonical(c, [3.0, -4.0, 0.5], 2.1, 4.3), p, atol=1e-5)


def test_box_corners_are_inside_and_ordered():
    boxes = Boxes([[1, 2, 3]], [[4, 2, 1.5]], [np.pi / 2])
    corners = box_corners(boxes)[0]
    # yaw 90 deg: the front (+x of the box) points to +y; first corner is front-left.
    np.testing.assert_allclose(corners[0], [1 - 1, 2 + 2, 3 - 0.75], atol=1e-12)
    np.testing.assert_allclose(corners.mean(axis=0), [1, 2, 3], atol=1e-12)
    assert (corners[:4, 2] < corners[4:, 2]).all()


def test_iou_bev_pairs_are_the_matrix_entries():
    _, boxes = random_scene(np.random.default_rng(6), n_points=10, n_boxes=30)
    i, j = np.nonzero(circles_meet(boxes, boxes))
    assert len(i) > len(boxes)  # the clustered boxes meet
    np.testing.assert_array_equal(iou_bev_pairs(boxes, i, j), iou_bev(boxes, boxes)[i, j])
    assert (iou_bev(boxes, boxes)[~circles_meet(boxes, boxes)] == 0).all()


def test_iou_axis_aligned_and_rotated_cases():
    a = Boxes([[0, 0, 0]], [[2, 2, 2]], [0.0])
    b = Boxes([[1, 0, 0], [0, 0, 1], [10, 0, 0], [0, 0, 0]], [[2, 2, 2], [2, 2, 2], [1, 1, 1], [2, 2, 2]],
              [0.0, 0.0, 0.0, np.pi / 4])
    bev = iou_bev(a, b)[0]
    np.testing.assert_allclose(bev[:3], [2 / 6, 1.0, 0.0], atol=1e-12)
    # Square and the same square rotated 45 deg: intersection is a regular octagon.
    octagon = 8 * (np.sqrt(2) - 1)  # area for a square of side 2
    np.testing.assert_allclose(bev[3], octagon / (8 - octagon), atol=1e-9)
    d3 = iou_3d(a, b)[0]
    np.testing.assert_allclose(d3[:3], [4 / 12, 4 / 12, 0.0], atol=1e-12)
    np.testing.assert_allclose(iou_bev(b, b).diagonal(), 1.0, atol=1e-9)


def clip_area(subject, clip):
    """Reference: Sutherland-Hodgman clipping of one convex polygon by another, in Python."""
    poly = [tuple(p) for p in subject]
    for i in range(len(clip)):
        a, b = clip[i], clip[(i + 1) % len(clip)]
        side = lambda p, a=a, b=b: (b[0] - a[0]) * (p[1] - a[1]) - (b[1] - a[1]) * (p[0] - a[0])  # noqa: E731
        out = []
        for j in range(len(poly)):
            p, q = poly[j], poly[(j + 1) % len(poly)]
            sp, sq = side(p), side(q)
            if sp >= 0:
                out.append(p)
            if (sp >= 0) != (sq >= 0):
                t = sp / (sp - sq)
                out.append((p[0] + t * (q[0] - p[0]), p[1] + t * (q[1] - p[1])))
        poly = out
        if not poly:
            return 0.0
    x, y = np.array(poly).T
    return 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def test_polygon_intersection_against_clipping_reference():
    rng = np.random.default_rng(2)
    a = Boxes(rng.uniform(-1, 1, (200, 3)), rng.uniform(0.5, 3, (200, 3)), rng.uniform(-np.pi, np.pi, 200))
    b = Boxes(rng.uniform(-1, 1, (200, 3)), rng.uniform(0.5, 3, (200, 3)), rng.uniform(-np.pi, np.pi, 200))
    b.yaw[:10] = a.yaw[:10]  # parallel edges (degenerate crossings)
    b.center[10:20] = a.center[10:20]
    ca, cb = box_corners(a)[:, :4, :2], box_corners(b)[:, :4, :2]
    area = polygon_intersection_area(ca, cb)
    ref = np.array([clip_area(p, q) for p, q in zip(ca, cb)])
    assert (ref > 0).sum() > 100
    np.testing.assert_allclose(area, ref, atol=1e-9)
    np.testing.assert_allclose(area, polygon_intersection_area(cb, ca), atol=1e-9)
    # Pairwise matrix agrees with the per-pair areas on its diagonal.
    inter = iou_bev(a, b).diagonal() * (a.size[:, 0] * a.size[:, 1] + b.size[:, 0] * b.size[:, 1])
    np.testing.assert_allclose(inter / (1 + iou_bev(a, b).diagonal()), ref, atol=1e-9)
