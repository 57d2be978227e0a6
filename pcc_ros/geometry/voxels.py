"""AML's voxel grids: reference occupancy + SDF from complete surfaces, observations with
ray-cast free space, batched and exact.

Two grids, both with AML's array axes ``H x W x D = 24 x 54 x 24`` (axis 0 = height z,
index 0 at the bottom; axis 1 = length x, index 0 at the rear; axis 2 = width y, index 0
on the right):

* :data:`BOX_GRID` (what AML uses): the *box frame*, the canonical frame divided per axis
  by the box's aspect ``(1, w / l, h / l)``, so every box is the cube ``[-0.5, 0.5]^3``
  (:func:`to_box_frame`). The grid spans ``[-0.6, 0.6]^3``: 0.1 of the box on every side.
  Voxel edges are 1.2 / 54 = 0.0222 box lengths and 1.2 / 24 = 0.05 box widths / heights
  (9.8 x 9 x 7.5 cm for a 4.4 x 1.8 x 1.5 m car). A decoded shape is stretched back by the
  box, so a tall van box gets a tall completion.
* :data:`AML_GRID`: the fixed *canonical* frame (box centre, box length = 1,
  ``x in [-0.6, 0.6]``, ``y, z in [-0.3, 0.3]``), where the box's width and height are
  not used. AML's first shipped weights used it (``frame: canonical``).

Observations (:func:`observation_grids`): ``occupied`` voxels hold a point; ``free`` voxels
are crossed by a LiDAR ray between the sensor origin and a point (stopping ``stop`` voxels
short of the point, so noise never carves the surface); the rest is unobserved (AML's ``⊥``).
The traversal is exact: a ray segment visits exactly the voxels on either side of each
grid plane it crosses, which are enumerated for all rays of all instances at once
(no loop over rays, points or instances).

Reference shapes (:func:`reference_grids`): from a dense complete surface sample
(SynthCars' ``shapes/`` clouds), occupancy = "on or inside the surface" (voxels holding a
surface sample, plus everything the outside cannot reach through 6-connected empty voxels)
and a signed distance (negative inside, in voxel units, truncated at ``truncation``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from pcc_ros.errors import DataError
from pcc_ros.geometry.sampling import cloud_seed
from pcc_ros.geometry.segments import positions_in_runs


@dataclass(frozen=True)
class GridSpec:
    """An axis-aligned grid in the canonical frame.

    Attributes:
        resolution: ``(H, L, W)`` voxels = (height z, length x, width y).
        lower, upper: canonical ``(x, y, z)`` corners of the grid box.
    """

    resolution: tuple[int, int, int] = (24, 54, 24)
    lower: tuple[float, float, float] = (-0.6, -0.3, -0.3)
    upper: tuple[float, float, float] = (0.6, 0.3, 0.3)

    @property
    def dims_xyz(self) -> np.ndarray:
        """Voxel counts in (x, y, z) order."""
        h, length, w = self.resolution
        return np.array([length, w, h], dtype=np.int64)

    @property
    def voxel_size(self) -> np.ndarray:
        """Canonical (x, y, z) edge lengths of one voxel."""
        return (np.asarray(self.upper, np.float64) - np.asarray(self.lower, np.float64)) / self.dims_xyz

    @property
    def mean_voxel(self) -> float:
        """Mean edge length (the unit of the SDF)."""
        return float(self.voxel_size.mean())

    def to_voxel(self, canonical: np.ndarray) -> np.ndarray:
        """Continuous voxel coordinates ``(..., 3)`` in (x, y, z) order (voxel i spans [i, i+1))."""
        return (np.asarray(canonical, np.float64)[..., :3] - np.asarray(self.lower)) / self.voxel_size

    def from_hlw(self, hlw: np.ndarray) -> np.ndarray:
        """Canonical (x, y, z) of continuous array coordinates (h, l, w); integers are voxel centres."""
        hlw = np.asarray(hlw, np.float64)
        xyz = np.stack([hlw[..., 1], hlw[..., 2], hlw[..., 0]], axis=-1) + 0.5
        return np.asarray(self.lower) + xyz * self.voxel_size

    def centers(self) -> np.ndarray:
        """``(H, L, W, 3)`` canonical voxel centres."""
        h, length, w = self.resolution
        idx = np.stack(np.meshgrid(np.arange(h), np.arange(length), np.arange(w), indexing="ij"), axis=-1)
        return self.from_hlw(idx)

    def flat_index(self, ixyz: np.ndarray) -> np.ndarray:
        """Flat index into an ``(H, L, W)`` array of integer (x, y, z) voxel indices."""
        _, length, w = self.resolution
        return (ixyz[..., 2] * length + ixyz[..., 0]) * w + ixyz[..., 1]


#: AML's grid in the canonical frame (paper: 24 x 54 x 24); the first shipped weights' frame.
AML_GRID = GridSpec()
#: AML's grid in the box frame (:func:`to_box_frame`): the box is [-0.5, 0.5]^3, 0.1 of padding.
BOX_GRID = GridSpec((24, 54, 24), (-0.6, -0.6, -0.6), (0.6, 0.6, 0.6))


def box_aspect(size: np.ndarray) -> np.ndarray:
    """``(..., 3)`` box sizes (l, w, h) -> aspects ``(1, w / l, h / l)``: the canonical extent of the box."""
    size = np.asarray(size, np.float64)
    if not (np.isfinite(size).all() and (size > 0).all()):
        raise DataError(f"box size must be positive and finite, got {size.tolist()}")
    return size / size[..., :1]


def to_box_frame(canonical: np.ndarray, aspect: np.ndarray) -> np.ndarray:
    """Canonical ``(N, 3)`` points -> the box frame, where the box is ``[-0.5, 0.5]^3``."""
    return np.asarray(canonical, np.float64)[..., :3] / np.asarray(aspect, np.float64)


def from_box_frame(points: np.ndarray, aspect: np.ndarray) -> np.ndarray:
    """Exact inverse of :func:`to_box_frame`."""
    return np.asarray(points, np.float64)[..., :3] * np.asarray(aspect, np.float64)


def _cloud(points: np.ndarray, what: str) -> np.ndarray:
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] < 3:
        raise DataError(f"{what}: expected (N, 3) points, got shape {pts.shape}")
    return pts[:, :3].astype(np.float64, copy=False)


def occupancy_grid(points: np.ndarray, spec: GridSpec = AML_GRID) -> np.ndarray:
    """``(H, L, W)`` bool: voxels holding at least one point (points outside the grid ignored)."""
    g = np.floor(spec.to_voxel(_cloud(points, "occupancy_grid"))).astype(np.int64)
    inside = ((g >= 0) & (g < spec.dims_xyz)).all(axis=1)
    out = np.zeros(int(np.prod(spec.resolution)), dtype=bool)
    out[spec.flat_index(g[inside])] = True
    return out.reshape(spec.resolution)


# --------------------------------------------------------------------------- ray casting


def _inside(ixyz: np.ndarray, spec: GridSpec) -> np.ndarray:
    """Rows of integer voxel indices inside the grid (negatives wrap to huge unsigned values)."""
    u = ixyz.view(np.uint64)  # int64 rows, C-contiguous
    dims = spec.dims_xyz
    return (u[:, 0] < dims[0]) & (u[:, 1] < dims[1]) & (u[:, 2] < dims[2])


def _mark(flat: np.ndarray, spec: GridSpec, instance: np.ndarray, ixyz: np.ndarray) -> None:
    inside = _inside(np.ascontiguousarray(ixyz, dtype=np.int64), spec)
    n = int(np.prod(spec.resolution))
    flat[instance[inside] * n + spec.flat_index(ixyz[inside])] = True


def ray_voxels(
    origins: np.ndarray,
    ends: np.ndarray,
    ray_instance: np.ndarray,
    count: int,
    spec: GridSpec = AML_GRID,
) -> np.ndarray:
    """``(count, H, L, W)`` bool: the voxels each segment ``origin -> end`` passes through.

    Exact traversal, vectorised over all segments: every voxel a segment enters lies on one
    side of a grid plane it crosses (or holds the whole segment), so the voxels on both sides
    of every crossing plus the voxel of each segment's midpoint are exactly the visited set
    (up to crossings through an edge or corner, a measure-zero event).

    Args:
        origins, ends: ``(R, 3)`` segment ends in *voxel coordinates* (x, y, z).
        ray_instance: ``(R,)`` grid (instance) each segment belongs to, in ``[0, count)``.
    """
    dims = spec.dims_xyz.astype(np.float64)
    flat = np.zeros(count * int(np.prod(spec.resolution)), dtype=bool)
    if len(origins) == 0:
        return flat.reshape(count, *spec.resolution)
    o = np.asarray(origins, np.float64)
    d = np.asarray(ends, np.float64) - o
    inst = np.asarray(ray_instance, np.int64)
    # Clip every segment to the grid box (slab method); t in [0, 1] along the segment.
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        ta, tb = -o * inv, (dims - o) * inv
    moving = d != 0
    inside_slab = (o >= 0) & (o <= dims)
    t_near = np.where(moving, np.minimum(ta, tb), np.where(inside_slab, -np.inf, np.inf))
    t_far = np.where(moving, np.maximum(ta, tb), np.where(inside_slab, np.inf, -np.inf))
    t0 = np.maximum(t_near.max(axis=1), 0.0)
    t1 = np.minimum(t_far.min(axis=1), 1.0)
    keep = t1 > t0
    o, d, inst, t0, t1 = o[keep], d[keep], inst[keep], t0[keep], t1[keep]
    if len(o) == 0:
        return flat.reshape(count, *spec.resolution)
    # The voxel holding each segment's midpoint (the whole segment when it crosses no plane).
    mid = o + 0.5 * (t0 + t1)[:, None] * d
    _mark(flat, spec, inst, np.floor(mid).astype(np.int64))
    entry, exit_ = o + t0[:, None] * d, o + t1[:, None] * d
    lo, hi = np.minimum(entry, exit_), np.maximum(entry, exit_)
    first = np.floor(lo).astype(np.int64) + 1  # planes k with lo < k < hi
    last = np.ceil(hi).astype(np.int64) - 1
    counts = np.maximum(last - first + 1, 0)  # (R, 3)
    for axis in range(3):  # three axes, each vectorised over all crossings of all segments
        n_axis = counts[:, axis]
        total = int(n_axis.sum())
        if total == 0:
            continue
        seg = np.repeat(np.arange(len(o)), n_axis)
        offset = positions_in_runs(n_axis)
        plane = first[seg, axis] + offset
        t = (plane - o[seg, axis]) / d[seg, axis]
        point = o[seg] + t[:, None] * d[seg]
        cell = np.floor(point).astype(np.int64)
        for side in (plane - 1, plane):
            cell[:, axis] = side
            _mark(flat, spec, inst[seg], cell)
    return flat.reshape(count, *spec.resolution)


def observation_grids(
    clouds: Sequence[np.ndarray],
    origins: np.ndarray,
    spec: GridSpec = AML_GRID,
    stop: float = 1.0,
    max_rays: int | None = None,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Occupied and ray-cast free space of a batch of canonical observations.

    Args:
        clouds: ``B`` canonical ``(N_i, 3)`` clouds.
        origins: ``(B, 3)`` sensor origin of each cloud in its canonical frame.
        stop: rays end this many voxels (mean edge) short of their point.
        max_rays: cast at most this many rays per cloud (a random subset: neighbouring rays
            sweep the same voxels; ``None``: every point). Occupancy always uses every point.
        seed: seed of the ray subset (per cloud: the subset depends only on the cloud).

    Returns:
        ``occupied``, ``free``: bool ``(B, H, L, W)``; ``free`` never overlaps ``occupied``.
    """
    b = len(clouds)
    origins = np.asarray(origins, np.float64).reshape(b, 3) if b else np.zeros((0, 3))
    if not np.isfinite(origins).all():
        raise DataError("observation_grids: non-finite sensor origin")
    pts = [_cloud(c, f"cloud {i}") for i, c in enumerate(clouds)]
    lengths = np.array([len(p) for p in pts], dtype=np.int64)
    allpts = np.concatenate(pts) if b else np.zeros((0, 3))
    inst = np.repeat(np.arange(b), lengths)
    g = spec.to_voxel(allpts)
    n = int(np.prod(spec.resolution))
    occupied = np.zeros(b * n, dtype=bool)
    _mark(occupied, spec, inst, np.floor(g).astype(np.int64))
    occupied = occupied.reshape(b, *spec.resolution)
    if max_rays is not None and (lengths > max_rays).any():
        picks = []
        starts = np.cumsum(lengths) - lengths
        for i in range(b):  # loop over instances: one seeded subset each
            if lengths[i] > max_rays:
                rng = np.random.default_rng(cloud_seed(pts[i], seed))
                picks.append(starts[i] + np.sort(rng.choice(lengths[i], max_rays, replace=False)))
            else:
                picks.append(starts[i] + np.arange(lengths[i]))
        sel = np.concatenate(picks)
        g, inst = g[sel], inst[sel]
    o = spec.to_voxel(origins)[inst]
    ray = g - o
    norm = np.linalg.norm(ray, axis=1)
    scale = np.clip(1.0 - stop / np.maximum(norm, 1e-12), 0.0, 1.0)
    free = ray_voxels(o, o + ray * scale[:, None], inst, b, spec)
    return occupied, free & ~occupied


def estimate_origin(cloud: np.ndarray, distance: float = 3.5, height: float = 0.3) -> np.ndarray:
    """A plausible canonical sensor origin when none is known: on the side the points face.

    A LiDAR sees the faces of a car that point toward it, so the points' centroid in the
    ground plane leans toward the sensor. The origin is put ``distance`` box lengths away
    in that direction, ``height`` above the box centre (a roof-mounted LiDAR ~1 m above a
    car's centre for a 4 m car). Used only when the caller gives no :class:`SceneContext`.
    """
    pts = _cloud(cloud, "estimate_origin")
    c = pts[:, :2].mean(axis=0)
    norm = float(np.linalg.norm(c))
    direction = c / norm if norm > 1e-6 else np.array([0.0, 1.0])
    return np.array([direction[0] * distance, direction[1] * distance, height])


# --------------------------------------------------------------------------- reference shapes


def reference_grids(
    surface: np.ndarray, spec: GridSpec = AML_GRID, truncation: float = 3.0
) -> tuple[np.ndarray, np.ndarray]:
    """Occupancy and truncated SDF of a complete shape given by dense surface samples.

    Args:
        surface: ``(M, 3)`` canonical samples of the closed outer surface (SynthCars:
            16384 uniform-by-area samples, about 4x denser than a voxel face needs).
        truncation: SDF magnitude cap, voxels.

    Returns:
        ``occupancy`` bool ``(H, L, W)`` (on or inside) and ``sdf`` float32 ``(H, L, W)``
        (voxel steps, negative inside). The SDF's magnitude is the distance from the voxel
        centre to the nearest surface sample; its sign is ``-`` for enclosed voxels, ``+``
        for voxels reachable from outside, and, for voxels holding the surface, the side
        whose region (enclosed interior or outside) is nearer.
    """
    from scipy import ndimage
    from scipy.spatial import cKDTree

    pts = _cloud(surface, "reference surface")
    if len(pts) < 4:
        raise DataError(f"reference surface has {len(pts)} points; need a dense sample")
    shell = occupancy_grid(pts, spec)
    # A sample-based shell can miss a voxel the surface only grazes, leaving a 6-connected
    # gap; filling the shell thickened by one voxel and peeling that layer off again closes it.
    thick = ndimage.binary_dilation(shell)
    filled = ndimage.binary_erosion(ndimage.binary_fill_holes(thick), border_value=0) | shell
    interior = filled & ~shell
    exterior = ~filled
    vox = spec.voxel_size[[2, 0, 1]]  # (h, l, w) spacing
    # distances in voxel steps along each axis (the box grid's voxels are ~cubic in metres,
    # not in box units); for a grid of near-cubic voxels this is the distance / voxel edge
    distance, _ = cKDTree(spec.to_voxel(pts)).query(spec.to_voxel(spec.centers().reshape(-1, 3)), workers=1)
    distance = distance.reshape(spec.resolution)
    d_out = ndimage.distance_transform_edt(~exterior, sampling=vox) if exterior.any() else np.full(shell.shape, np.inf)
    d_in = ndimage.distance_transform_edt(~interior, sampling=vox) if interior.any() else np.full(shell.shape, np.inf)
    inside = interior | (shell & (d_in <= d_out))
    sdf = np.where(inside, -distance, distance)
    return filled, np.clip(sdf, -truncation, truncation).astype(np.float32)
