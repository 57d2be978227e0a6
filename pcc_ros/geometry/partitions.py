"""Partitions of canonical car clouds that the backends need.

- PointPnCNet: eight octants split by the canonical coordinate planes, neighbouring
  octants overlapping slightly so no seam appears between local decoders
  (paper: 0.02 m on KITTI, i.e. about 0.005 in canonical units for a 4 m car).
- TraPCC: front and back halves (x >= 0 is the front in the canonical frame).
- AML: a 24 x 54 x 24 (height x length x width) voxel grid over the box padded by a
  quarter of its size on every side, with observed occupancy and the free space swept
  by the LiDAR rays between the sensor origin and each point.

All functions take canonical ``(N, 3)`` clouds (see :mod:`pcc_ros.geometry.canonical`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pcc_ros.errors import DataError

#: PointPnCNet's KITTI overlap (0.02 m) in canonical units for a 4 m car.
OCTANT_OVERLAP = 0.005
#: AML's grid: H x W x D = height x length x width voxels.
AML_RESOLUTION = (24, 54, 24)
#: AML's padding, as a fraction of the box size added on every side.
AML_PADDING = 0.25


def _canonical(points: np.ndarray) -> np.ndarray:
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] < 3:
        raise DataError(f"canonical points must be (N, >=3), got shape {pts.shape}")
    return pts[:, :3]


def octant_index(canonical: np.ndarray) -> np.ndarray:
    """Strict octant of each point: ``bit0 = x >= 0`` (front), ``bit1 = y >= 0`` (left), ``bit2 = z >= 0`` (top)."""
    pts = _canonical(canonical)
    return (pts[:, 0] >= 0).astype(np.int64) | ((pts[:, 1] >= 0) << 1) | ((pts[:, 2] >= 0) << 2)


def octant_masks(canonical: np.ndarray, overlap: float = OCTANT_OVERLAP) -> np.ndarray:
    """``(N, 8)`` membership of each point in the eight octants (column = :func:`octant_index`).

    A point within ``overlap`` (canonical units) of a coordinate plane belongs to the
    octants on both sides, so every point is in at least one octant and points near
    the planes are shared by neighbours.
    """
    if overlap < 0:
        raise ValueError(f"overlap must be >= 0, got {overlap}")
    pts = _canonical(canonical)
    positive = pts >= -overlap  # (N, 3): may belong to the >= 0 side of each axis
    negative = pts < overlap  # may belong to the < 0 side
    bits = np.arange(8)
    sides = ((bits[:, None] >> np.arange(3)[None, :]) & 1).astype(bool)  # (8, 3)
    member = np.where(sides[None], positive[:, None, :], negative[:, None, :])  # (N, 8, 3)
    return member.all(axis=2)


def front_back_masks(canonical: np.ndarray, overlap: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """TraPCC's halves: ``(front, back)`` boolean masks (front is ``x >= 0``), optional overlap."""
    pts = _canonical(canonical)
    return pts[:, 0] >= -overlap, pts[:, 0] < overlap


@dataclass
class VoxelGrid:
    """An AML observation grid.

    Array axes are (height z, length x, width y), i.e. AML's H x W x D. ``occupied``:
    voxels containing a point; ``free``: voxels a ray crossed before reaching its point
    (never occupied); everything else is unobserved (AML's ``⊥``).

    Attributes:
        occupied, free: boolean ``(H, W, D)``.
        lower: canonical ``(x, y, z)`` of the grid's minimum corner.
        voxel_size: canonical ``(x, y, z)`` edge lengths of one voxel.
    """

    occupied: np.ndarray
    free: np.ndarray
    lower: np.ndarray
    voxel_size: np.ndarray

    @property
    def unobserved(self) -> np.ndarray:
        return ~(self.occupied | self.free)

    def centers(self) -> np.ndarray:
        """``(H, W, D, 3)`` canonical (x, y, z) voxel centres."""
        h, w, d = self.occupied.shape
        iz, ix, iy = np.meshgrid(np.arange(h), np.arange(w), np.arange(d), indexing="ij")
        grid = np.stack([ix, iy, iz], axis=-1) + 0.5
        return self.lower + grid * self.voxel_size

    def to_canonical_points(self, mask: np.ndarray | None = None) -> np.ndarray:
        """Canonical centres of the voxels in ``mask`` (default: occupied)."""
        return self.centers()[self.occupied if mask is None else mask]


def grid_bounds(
    box_size: np.ndarray, resolution: tuple[int, int, int] = AML_RESOLUTION, padding: float = AML_PADDING
) -> tuple[np.ndarray, np.ndarray]:
    """Canonical lower corner and voxel size of the padded box grid for a ``(l, w, h)`` box."""
    size = np.asarray(box_size, dtype=np.float64).reshape(3)
    if not (np.isfinite(size).all() and (size > 0).all()):
        raise DataError(f"box size must be positive and finite, got {size.tolist()}")
    extent = size / size[0] * (1.0 + 2.0 * padding)  # canonical (x, y, z) extent of the padded box
    h, w, d = resolution
    return -extent / 2.0, extent / np.array([w, d, h], dtype=np.float64)


def voxelize(
    canonical: np.ndarray,
    origin: np.ndarray,
    box_size: np.ndarray,
    resolution: tuple[int, int, int] = AML_RESOLUTION,
    padding: float = AML_PADDING,
    step: float = 0.5,
    stop: float = 1.0,
    chunk: int = 4096,
) -> VoxelGrid:
    """AML occupancy + free space of one canonical observation.

    Args:
        canonical: ``(N, 3)`` canonical points of the observation.
        origin: the sensor origin in the same canonical frame (rays start there).
        box_size: the box's metric ``(length, width, height)``; the padded box is scaled
            onto the grid per axis ("car scaled to the grid").
        resolution: ``(H, W, D)`` = (height, length, width) voxels.
        padding: fraction of the box size added on every side.
        step: ray sampling step in voxels (<= 0.5 never skips a voxel a ray crosses
            by more than half a voxel).
        stop: rays stop this many voxels short of their point, so free space is never
            at or behind an observed point.
        chunk: rays processed per vectorised block (bounds memory).
    """
    pts = _canonical(canonical).astype(np.float64)
    lower, voxel = grid_bounds(box_size, resolution, padding)
    h, w, d = resolution
    dims = np.array([w, d, h], dtype=np.float64)  # grid extent in voxel units, (x, y, z) order
    occupied = np.zeros((h, w, d), dtype=bool)
    free = np.zeros((h, w, d), dtype=bool)
    if len(pts) == 0:
        return VoxelGrid(occupied, free, lower, voxel)
    g = (pts - lower) / voxel  # continuous voxel coordinates
    o = (np.asarray(origin, dtype=np.float64).reshape(3) - lower) / voxel
    idx = np.floor(g).astype(np.int64)
    inside = ((idx >= 0) & (idx < dims.astype(np.int64))).all(axis=1)
    occupied[idx[inside, 2], idx[inside, 0], idx[inside, 1]] = True

    max_samples = int(np.ceil(np.linalg.norm(dims) / step)) + 2
    free_flat = np.zeros(h * w * d, dtype=bool)
    for s in range(0, len(g), chunk):  # loop over blocks of rays, each block vectorised
        p = g[s : s + chunk]
        ray = p - o  # (R, 3)
        length = np.linalg.norm(ray, axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / ray
            t0 = (0.0 - o) * inv
            t1 = (dims - o) * inv
        # Slab clipping of the segment to the grid box; axis-parallel rays that lie
        # outside a slab never enter (their t range is empty / NaN).
        t_lo = np.nanmax(np.where(ray != 0, np.minimum(t0, t1), np.where((o >= 0) & (o < dims), -np.inf, np.inf)),
                         axis=1)
        t_hi = np.nanmin(np.where(ray != 0, np.maximum(t0, t1), np.where((o >= 0) & (o < dims), np.inf, -np.inf)),
                         axis=1)
        t_start = np.maximum(t_lo, 0.0)
        t_end = np.minimum(t_hi, 1.0 - stop / np.maximum(length, 1e-12))
        k = np.arange(max_samples)
        t = t_start[:, None] + k[None, :] * (step / np.maximum(length, 1e-12))[:, None]  # (R, S)
        valid = t < t_end[:, None]
        samples = o + t[..., None] * ray[:, None, :]  # (R, S, 3)
        vi = np.floor(samples[valid]).astype(np.int64)
        ok = ((vi >= 0) & (vi < dims.astype(np.int64))).all(axis=1)
        vi = vi[ok]
        free_flat[(vi[:, 2] * w + vi[:, 0]) * d + vi[:, 1]] = True
    free = free_flat.reshape(h, w, d) & ~occupied
    return VoxelGrid(occupied, free, lower, voxel)
