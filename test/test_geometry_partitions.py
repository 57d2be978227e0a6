"""Resampling, FPS, octants, front/back halves and the AML voxel grid."""

from __future__ import annotations

import numpy as np
import pytest

from pcc_ros.errors import DataError
from pcc_ros.geometry.partitions import (
    AML_RESOLUTION,
    front_back_masks,
    grid_bounds,
    octant_index,
    octant_masks,
    voxelize,
)
from pcc_ros.geometry.sampling import farthest_point_indices, farthest_point_sample, resample, resample_indices


def test_resample_modes():
    rng = np.random.default_rng(0)
    pts = np.arange(30, dtype=np.float32).reshape(10, 3)
    idx = resample_indices(10, 6, rng)
    assert len(np.unique(idx)) == 6  # enough points: no duplicates
    idx = resample_indices(10, 25, rng)
    assert len(idx) == 25 and set(idx[:10]) == set(range(10))  # every point kept, then padding
    assert resample(pts, 25, np.random.default_rng(1)).shape == (25, 3)
    same = resample(pts, 7, np.random.default_rng(3)), resample(pts, 7, np.random.default_rng(3))
    np.testing.assert_array_equal(*same)
    assert len(resample_indices(10, 50, rng, replace=True)) == 50
    with pytest.raises(DataError):
        resample_indices(10, 11, rng, replace=False)
    with pytest.raises(DataError, match="empty"):
        resample(np.zeros((0, 3)), 5, rng)


def test_farthest_point_sampling_spreads_points():
    rng = np.random.default_rng(0)
    # A dense blob plus four far corners: FPS must pick the corners early.
    blob = rng.normal(0, 0.01, (2000, 3))
    corners = np.array([[5, 5, 0], [-5, 5, 0], [5, -5, 0], [-5, -5, 0]], dtype=np.float64)
    pts = np.r_[blob, corners]
    idx = farthest_point_indices(pts, 5)
    assert set(range(2000, 2004)) <= set(idx.tolist())
    assert len(np.unique(idx)) == 5
    # Coverage: FPS of a uniform cloud has a smaller covering radius than random picks.
    cloud = rng.uniform(-1, 1, (3000, 3))
    fps = farthest_point_sample(cloud, 64)
    rnd = cloud[rng.choice(3000, 64, replace=False)]
    cover = lambda s: np.sqrt(((cloud[:, None] - s[None]) ** 2).sum(-1)).min(1).max()  # noqa: E731
    assert cover(fps) < cover(rnd)
    assert farthest_point_sample(cloud[:3], 5).shape == (5, 3)


def test_octants_cover_every_point_with_overlap():
    rng = np.random.default_rng(0)
    pts = rng.uniform(-0.5, 0.5, (5000, 3))
    pts[:200, 0] = rng.uniform(-0.004, 0.004, 200)  # near the x plane
    masks = octant_masks(pts, overlap=0.005)
    assert masks.shape == (5000, 8)
    assert masks.any(axis=1).all()  # every point covered
    strict = octant_index(pts)
    assert masks[np.arange(5000), strict].all()  # includes its own octant
    # Points within the overlap of the x plane are in both the front and back octant.
    np.testing.assert_array_equal(masks[:200].sum(axis=1) >= 2, True)
    far = (np.abs(pts) > 0.005).all(axis=1)
    np.testing.assert_array_equal(masks[far].sum(axis=1), 1)
    no_overlap = octant_masks(pts, overlap=0.0)
    np.testing.assert_array_equal(no_overlap.sum(axis=1), 1)
    # Octant bits: bit0 front (x >= 0), bit1 left (y >= 0), bit2 top (z >= 0).
    assert octant_index(np.array([[0.1, 0.1, 0.1], [-0.1, 0.1, -0.1]])).tolist() == [7, 2]


def test_front_back_halves():
    pts = np.array([[0.3, 0, 0], [-0.2, 0, 0], [0.001, 0, 0]])
    front, back = front_back_masks(pts)
    assert front.tolist() == [True, False, True] and back.tolist() == [False, True, False]
    front, back = front_back_masks(pts, overlap=0.01)
    assert (front & back).tolist() == [False, False, True]


def test_voxel_grid_geometry():
    lower, voxel = grid_bounds([4.0, 1.8, 1.5])
    np.testing.assert_allclose(lower, -np.array([1.0, 0.45, 0.375]) * 1.5 / 2)
    np.testing.assert_allclose(voxel * [54, 24, 24], np.array([1.0, 0.45, 0.375]) * 1.5)
    grid = voxelize(np.array([[0.0, 0.0, 0.0], [0.49, 0.2, 0.15], [3.0, 0, 0]]), [5.0, 0, 0], [4.0, 1.8, 1.5])
    assert grid.occupied.shape == AML_RESOLUTION
    assert grid.occupied.sum() == 2  # the point outside the padded box is ignored
    # Voxel centres map back: the occupied centres are within half a voxel of the points.
    centres = grid.to_canonical_points()
    assert np.abs(centres - np.array([[0.0, 0.0, 0.0]])).min(axis=0).max() <= voxel.max() / 2 + 1e-9


def test_free_space_never_behind_an_observed_point():
    rng = np.random.default_rng(4)
    size = np.array([4.0, 1.8, 1.5])
    origin = np.array([3.0, 1.0, 0.3])  # sensor ahead-left of the car (12 m away)
    # A wall of points (the car's front face) at x = 0.4, facing the sensor.
    wall = np.c_[np.full(400, 0.4), rng.uniform(-0.2, 0.2, 400), rng.uniform(-0.15, 0.15, 400)]
    grid = voxelize(wall, origin, size)
    assert grid.free.sum() > 50 and grid.occupied.sum() > 20
    assert not (grid.free & grid.occupied).any()
    centres = grid.centers()
    _, voxel = grid_bounds(size)
    # Every free voxel lies entirely on the sensor's side of the wall plane.
    assert (centres[grid.free][:, 0] - voxel[0] / 2 >= 0.4 - 1e-9).all()  # sensor is at x = 3
    # Single rays: free voxels are strictly closer to the sensor than the point.
    for p in rng.uniform(-0.5, 0.5, (20, 3)) * [1, 0.45, 0.37]:
        g = voxelize(p[None], origin, size)
        if g.free.any():
            d_free = np.linalg.norm((centres[g.free] - origin) / voxel, axis=1)
            assert d_free.max() < np.linalg.norm((p - origin) / voxel)
    # The other side of the car (behind the wall from the sensor) stays unobserved.
    back = centres[..., 0] < -0.3
    assert not grid.free[back].any()


def test_voxelize_handles_axis_parallel_rays_and_empty_input():
    size = [4.0, 1.8, 1.5]
    g = voxelize(np.array([[0.2, 0.0, 0.0]]), [3.0, 0.0, 0.0], size)  # ray along -x only
    assert g.free.any()
    zs, _, ys = np.nonzero(g.free)
    assert len(set(zs.tolist())) == 1 and len(set(ys.tolist())) == 1
    empty = voxelize(np.zeros((0, 3)), [3.0, 0, 0], size)
    assert not empty.occupied.any() and not empty.free.any()
    with pytest.raises(DataError):
        voxelize(np.zeros((3, 3)), [3.0, 0, 0], [0.0, 1.0, 1.0])
