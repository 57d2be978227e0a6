"""Resampling point clouds to a fixed count: random (with / without replacement) and FPS.

Networks take fixed-size inputs; instances have anything from a handful to thousands
of points. Random resampling keeps the density statistics of the scan; farthest-point
sampling (FPS) spreads the points evenly, which suits targets and sparse inputs.
Seeds are always explicit (a ``numpy.random.Generator``), so datasets are reproducible.
"""

from __future__ import annotations

import hashlib

import numpy as np

from pcc_ros.errors import DataError


def cloud_seed(cloud: np.ndarray, seed: int = 0) -> int:
    """A seed derived from a cloud's bytes: deterministic per cloud, independent of batching."""
    digest = hashlib.blake2b(np.ascontiguousarray(cloud, dtype=np.float32).tobytes(), digest_size=8).digest()
    return (int.from_bytes(digest, "little") ^ (seed * 0x9E3779B97F4A7C15)) & 0xFFFF_FFFF_FFFF_FFFF


def resample_indices(count: int, n: int, rng: np.random.Generator, replace: bool | None = None) -> np.ndarray:
    """Indices of ``n`` of ``count`` points.

    ``replace=None`` (default) samples without replacement when there are enough points
    and otherwise keeps every point once and pads with random duplicates, so no
    observed point is ever dropped in favour of a duplicate. ``replace=True`` / ``False``
    force the mode (``False`` with too few points raises).
    """
    if count <= 0:
        raise DataError("cannot resample an empty point cloud")
    if n < 0:
        raise ValueError(f"n must be >= 0, got {n}")
    if replace is True:
        return rng.integers(0, count, n)
    if count >= n:
        return rng.permutation(count)[:n]
    if replace is False:
        raise DataError(f"cannot draw {n} points without replacement from {count}")
    return np.concatenate([rng.permutation(count), rng.integers(0, count, n - count)])


def resample(points: np.ndarray, n: int, rng: np.random.Generator, replace: bool | None = None) -> np.ndarray:
    """``n`` rows of ``points`` (see :func:`resample_indices` for the replacement rule)."""
    points = np.asarray(points)
    return points[resample_indices(len(points), n, rng, replace)]


def farthest_point_indices(points: np.ndarray, n: int, start: int = 0) -> np.ndarray:
    """Indices of ``n`` farthest-point samples of ``points`` (deterministic given ``start``).

    Iterates over the *samples* (each step is one vectorised distance update over all
    points), O(n * N). With fewer than ``n`` points, every point is returned first and
    the rest repeats the sequence.
    """
    pts = np.asarray(points, dtype=np.float64)[:, :3]
    count = len(pts)
    if count == 0:
        raise DataError("cannot sample an empty point cloud")
    if n <= 0:
        return np.zeros(0, dtype=np.int64)
    m = min(n, count)
    chosen = np.empty(m, dtype=np.int64)
    chosen[0] = start % count
    dist = np.sum((pts - pts[chosen[0]]) ** 2, axis=1)
    for i in range(1, m):  # loop over samples, not points
        chosen[i] = int(np.argmax(dist))
        np.minimum(dist, np.sum((pts - pts[chosen[i]]) ** 2, axis=1), out=dist)
    if m < n:
        chosen = np.resize(chosen, n)
    return chosen


def farthest_point_sample(points: np.ndarray, n: int, start: int = 0) -> np.ndarray:
    """``n`` farthest-point samples of ``points`` (rows, same dtype and columns)."""
    points = np.asarray(points)
    return points[farthest_point_indices(points, n, start)]
