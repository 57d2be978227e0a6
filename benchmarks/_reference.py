"""The per-frame geometry of main at 93cd59e, before the #19 filter and crop work, kept
verbatim (names unchanged) as the "today's pipeline" side of ``pcc bench pipeline`` and the
reference of ``pcc bench filter``; nothing else uses it.

:func:`original_geometry` swaps it into the pipeline for the duration of a block: the
crop stage (``bounded_crop``: the work estimate ``estimated_crop_pairs``, then ``crop_canonical``) and the evidence
filter's measurements (``evidence``). Not thread-safe: a process-wide switch for benchmarks.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import numpy as np

from pcc_ros.errors import DataError
from pcc_ros.geometry.boxes import _bev_corners, _check_boxes, box_corners, round_down_to, round_up_to
from pcc_ros.pipeline.evidence import (
    EVIDENCE_GROUND,
    EXPECTED_COLUMNS,
    GROUND_REACH,
    Evidence,
    SensorModel,
    _column_grid,
    _columns,
    _derive,
    angular_window,
    core_box,
    cover,
    ground_reach,
)
from pcc_ros.types import Boxes

CELL_FRACTION = 0.25
_AZ_BINS = 3600


def _group_by_box(pair_point: np.ndarray, pair_box: np.ndarray, n_boxes: int, *values: np.ndarray) -> list:
    """Split pair arrays per box; point indices stay ascending inside each box (93cd59e's
    grouping; the package's own pass yields its pairs already grouped by box)."""
    key = pair_box.astype(np.int16 if n_boxes < 32767 else np.int64)  # int16: radix sort
    order = np.argsort(key, kind="stable")
    ends = np.cumsum(np.bincount(pair_box, minlength=n_boxes)).tolist()
    starts = [0, *ends[:-1]]

    def split(a: np.ndarray) -> list[np.ndarray]:  # plain slices: np.split costs ~10 us per piece
        return [a[s:e] for s, e in zip(starts, ends)]

    out = [split(np.take(pair_point, order))]
    out.extend(split(np.take(v, order, axis=0)) for v in values)
    return out


@contextlib.contextmanager
def original_geometry() -> Iterator[None]:
    """Run the pipeline's crop, work estimate and evidence measurements as of 93cd59e."""
    import pcc_ros.pipeline.core as pipeline_module
    import pcc_ros.pipeline.filter as filter_module

    saved = (pipeline_module._bounded_crop, filter_module.evidence)
    pipeline_module._bounded_crop = bounded_crop
    # one thread; 93cd59e measured everything (the filter keeps what its rule weights); the
    # azimuth columns of ``cover`` (a term after 93cd59e) from the same pass's pairs; the profile
    # terms (after 93cd59e too, measured in the evidence's call today) by today's profile pass
    filter_module.evidence = original_evidence
    try:
        yield
    finally:
        pipeline_module._bounded_crop, filter_module.evidence = saved


def original_evidence(points: np.ndarray, boxes: Boxes, sensor=None, workers: int = 1, columns: bool = False,
                      profile=(), **_measured) -> Evidence:
    """:func:`pcc_ros.pipeline.evidence.evidence`'s signature over 93cd59e's measurements (one
    thread, every measurement), the ``profile`` terms by today's profile pass on its own."""
    from pcc_ros.pipeline.evidence_profile import profile_terms

    ev = evidence(points, boxes, sensor, columns=columns)
    if profile:
        ev.profile = profile_terms(points, boxes, sensor, measure=profile)
    return ev


def bounded_crop(points: np.ndarray, boxes: Boxes, cfg):
    """The crop stage as at 93cd59e: the work estimate, then the crop of the boxes that fit
    (the budget rule itself is unchanged: ``pipeline.core.crop_budget``)."""
    from pcc_ros.pipeline.core import crop_budget

    work = estimated_crop_pairs(points, boxes, cfg.box_margin)
    fits = crop_budget(work, boxes, cfg.max_crop_work)
    chosen = boxes if fits is None else boxes[fits]
    return (*crop_canonical(points, chosen, cfg.box_margin, cfg.ground_margin), fits, work)


def points_in_boxes(points: np.ndarray, boxes: Boxes, margin: float = 0.0, ground_margin: float = 0.0,
                    cell: float | None = None) -> list[np.ndarray]:
    pair_point, pair_box, _ = _pairs_in_boxes(points, boxes, margin, ground_margin, cell)
    if len(boxes) == 0:
        return []
    return _group_by_box(pair_point, pair_box, len(boxes))[0]


# ---------------------------------------------------------------- geometry/boxes.py at 93cd59e

def _candidate_pairs(
    xy: np.ndarray, boxes: Boxes, margin: float, cell: float | None
) -> tuple[np.ndarray, np.ndarray]:
    """(point index, box index) pairs whose BEV grid cell overlaps the box's BEV extent.

    Cost: a handful of vector operations over the scan plus work proportional to the
    candidate count; boxes are only touched to build a small cell -> boxes table.
    """
    corners = _bev_corners(boxes)
    lo = corners.min(axis=1) - margin  # (B, 2) axis-aligned BEV extents
    hi = corners.max(axis=1) + margin
    if cell is None:
        # Cells about the size of a car's width keep the table small and the
        # candidate overhead (points in cells but outside boxes) low.
        cell = float(np.clip(CELL_FRACTION * np.median(np.minimum(boxes.size[:, 0], boxes.size[:, 1])), 0.25, 4.0))
    origin = lo.min(axis=0)
    n_cells = np.floor((hi.max(axis=0) - origin) / cell).astype(np.int64) + 1
    if n_cells[0] * n_cells[1] > 1_000_000:  # boxes spread very far apart: coarser cells
        cell *= float(np.sqrt(n_cells[0] * n_cells[1] / 1_000_000.0)) * 1.01
        n_cells = np.floor((hi.max(axis=0) - origin) / cell).astype(np.int64) + 1
    nx, ny = int(n_cells[0]), int(n_cells[1])

    # Cell -> boxes table in CSR form (loops over boxes are replaced by repeat/arange).
    c0 = np.floor((lo - origin) / cell).astype(np.int64)
    c1 = np.floor((hi - origin) / cell).astype(np.int64)
    span = c1 - c0 + 1  # (B, 2)
    per_box = span[:, 0] * span[:, 1]
    box_of = np.repeat(np.arange(len(boxes)), per_box)
    local = np.arange(per_box.sum()) - np.repeat(np.cumsum(per_box) - per_box, per_box)
    cx = c0[box_of, 0] + local // span[box_of, 1]
    cy = c0[box_of, 1] + local % span[box_of, 1]
    # Keep only the cells that can touch the rotated box: the cell centre within the
    # (margin-enlarged) box grown by half a cell diagonal. Trims the AABB corners that a
    # yawed box leaves empty, which would otherwise become candidate points.
    ccx = origin[0] + (cx + 0.5) * cell - boxes.center[box_of, 0]
    ccy = origin[1] + (cy + 0.5) * cell - boxes.center[box_of, 1]
    cos, sin = np.cos(boxes.yaw[box_of]), np.sin(boxes.yaw[box_of])
    reach = cell * np.sqrt(0.5) + margin
    touch = (np.abs(cos * ccx + sin * ccy) <= boxes.size[box_of, 0] / 2 + reach) & (
        np.abs(-sin * ccx + cos * ccy) <= boxes.size[box_of, 1] / 2 + reach
    )
    box_of, cx, cy = box_of[touch], cx[touch], cy[touch]
    key = cx * ny + cy
    order = np.argsort(key, kind="stable")
    table_boxes = box_of[order]
    counts = np.bincount(key, minlength=nx * ny)
    starts = np.concatenate([[0], np.cumsum(counts)])
    # One pass over the scan: the cell of every point. float32, contiguous temporaries
    # and np.take (several times faster than fancy indexing) keep each step at tens of
    # microseconds for a 120k-point scan.
    inv = np.float32(1.0 / cell)
    with np.errstate(invalid="ignore"):
        gx = np.subtract(xy[:, 0], np.float32(origin[0]), dtype=np.float32)
        gx *= inv
        gy = np.subtract(xy[:, 1], np.float32(origin[1]), dtype=np.float32)
        gy *= inv
        inside = (gx >= 0) & (gx < nx) & (gy >= 0) & (gy < ny)  # NaN compares False
    pts = np.flatnonzero(inside)
    pkey = np.take(gx, pts).astype(np.int32) * np.int32(ny) + np.take(gy, pts).astype(np.int32)
    n_per_point = np.take(counts, pkey)
    hit = np.flatnonzero(n_per_point)
    pts, pkey, n_per_point = np.take(pts, hit), np.take(pkey, hit), np.take(n_per_point, hit)
    # Expand to (point, box) pairs in point order (CSR walk without a Python loop).
    pair_point = np.repeat(pts, n_per_point)
    if len(pair_point) == len(pts):  # no cell shared by two boxes: one box per point
        slot = np.take(starts, pkey)
    else:
        ends = np.cumsum(n_per_point)
        slot = np.repeat(np.take(starts, pkey) - ends + n_per_point, n_per_point) + np.arange(ends[-1])
    pair_box = np.take(table_boxes, slot)
    return pair_point, pair_box


def _pairs_in_boxes(
    points: np.ndarray,
    boxes: Boxes,
    margin: float,
    ground_margin: float,
    cell: float | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact (point, box) pairs plus the points' box-frame coordinates (metres)."""
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] < 3:
        raise DataError(f"points must be (N, >=3), got shape {pts.shape}")
    _check_boxes(boxes)
    if len(boxes) == 0 or len(pts) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3))
    pair_point, pair_box = _candidate_pairs(pts[:, :2], boxes, margin, cell)
    # Per-box parameters gathered per pair with np.take; the test runs in the scan's
    # precision (float32 for sensor data) on box-relative x/y. The z bounds are rounded
    # outward-exactly to that precision, so the bottom / top tests (where the ground
    # returns sit, right at the boundary) agree with an exact float64 test.
    dt = np.float32 if pts.dtype == np.float32 else np.float64
    half = boxes.size / 2.0
    zlo = round_up_to(boxes.center[:, 2] - half[:, 2] - margin + ground_margin, dt)
    zhi = round_down_to(boxes.center[:, 2] + half[:, 2] + margin, dt)
    table = np.stack(
        [
            boxes.center[:, 0], boxes.center[:, 1], boxes.center[:, 2],
            np.cos(boxes.yaw), np.sin(boxes.yaw),
            half[:, 0] + margin, half[:, 1] + margin,
        ],
        axis=0,
    ).astype(dt)
    cx, cy, cz, c, s, hl, hw = (np.take(col, pair_box) for col in table)
    pt = pts.T
    pz = np.take(pt[2], pair_point).astype(dt, copy=False)
    dx = np.take(pt[0], pair_point).astype(dt, copy=False) - cx
    dy = np.take(pt[1], pair_point).astype(dt, copy=False) - cy
    lx = c * dx + s * dy
    ly = c * dy - s * dx
    keep = (np.abs(lx) <= hl) & (np.abs(ly) <= hw) & (pz >= np.take(zlo, pair_box)) & (pz <= np.take(zhi, pair_box))
    keep = np.flatnonzero(keep)
    lx, ly = np.take(lx, keep), np.take(ly, keep)
    dz = np.take(pz, keep) - np.take(cz, keep)
    return np.take(pair_point, keep), np.take(pair_box, keep), np.stack([lx, ly, dz], axis=1)


def crop_canonical(
    points: np.ndarray,
    boxes: Boxes,
    margin: float = 0.0,
    ground_margin: float = 0.0,
    cell: float | None = None,
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Crop every box and express its points in the box's canonical car frame.

    Same as :func:`points_in_boxes` followed by
    :func:`pcc_ros.geometry.canonical.to_canonical` per box, but the rotation is computed
    once for all pairs (the exact test already needs it). Returns ``(indices, canonical)``,
    canonical points as float32 ``(n_i, 3)`` scaled by ``1 / length``.
    """
    pair_point, pair_box, local = _pairs_in_boxes(points, boxes, margin, ground_margin, cell)
    if len(boxes) == 0:
        return [], []
    canonical = (local / boxes.size[pair_box, 0:1]).astype(np.float32)
    indices, canon = _group_by_box(pair_point, pair_box, len(boxes), canonical)
    return indices, canon


# ---------------------------------------------------------------- pipeline.py at 93cd59e

def estimated_crop_pairs(points: np.ndarray, boxes: Boxes, margin: float = 0.0) -> np.ndarray:
    """Per box, the number of scan points within its footprint's axis-aligned bounding
    rectangle (an upper estimate of the points it crops), from a BEV count grid and its
    summed-area table:
    ``O(points + boxes)``, whatever the boxes' sizes."""
    if len(boxes) == 0 or len(points) == 0:
        return np.zeros(len(boxes), dtype=np.int64)
    xy = np.asarray(points[:, :2], dtype=np.float64)
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    cell = max(1.0, float((hi - lo).max()) / 1024.0)  # at most ~1024 x 1024 cells
    shape = np.floor((hi - lo) / cell).astype(np.int64) + 1
    cells = np.floor((xy - lo) / cell).astype(np.int64)
    grid = np.bincount(cells[:, 0] * shape[1] + cells[:, 1], minlength=int(shape.prod())).reshape(shape)
    table = np.zeros((shape[0] + 1, shape[1] + 1), dtype=np.int64)
    table[1:, 1:] = grid.cumsum(axis=0).cumsum(axis=1)
    # axis-aligned extent of the margin-enlarged, rotated footprint
    hl, hw = boxes.size[:, 0] / 2.0 + margin, boxes.size[:, 1] / 2.0 + margin
    c, s = np.abs(np.cos(boxes.yaw)), np.abs(np.sin(boxes.yaw))
    half = np.stack([hl * c + hw * s, hl * s + hw * c], axis=1)
    first = np.clip(np.floor((boxes.center[:, :2] - half - lo) / cell), 0, shape).astype(np.int64)
    last = np.clip(np.floor((boxes.center[:, :2] + half - lo) / cell) + 1, 0, shape).astype(np.int64)
    return (table[last[:, 0], last[:, 1]] - table[first[:, 0], last[:, 1]]
            - table[last[:, 0], first[:, 1]] + table[first[:, 0], first[:, 1]])


# ---------------------------------------------------------------- filter.py at 93cd59e

def _box_frame(boxes: Boxes, index: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    """Points ``xyz (P, 3)`` in the frame of box ``index (P,)`` (origin at its centre)."""
    c, s = np.cos(boxes.yaw[index]), np.sin(boxes.yaw[index])
    d = xyz - boxes.center[index]
    return np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]], axis=1)


def _slab(origin: np.ndarray, direction: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Entry and exit ray parameters of ``origin + t * direction`` through boxes ``[lo, hi]`` (rows)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / direction
        t1 = (lo - origin) * inv
        t2 = (hi - origin) * inv
        # fmax / fmin skip the NaN of a ray parallel to a slab starting on its plane
        tmin = np.fmax.reduce(np.minimum(t1, t2), axis=1)
        tmax = np.fmin.reduce(np.maximum(t1, t2), axis=1)
    return tmin, tmax


def _angular_window(boxes: Boxes) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per box: azimuth interval (lo, hi), conservative elevation interval (lo, hi), and
    whether the sensor sits outside the box's footprint (boxes around the sensor are not judged)."""
    corners = box_corners(boxes)
    centre_az = np.arctan2(boxes.center[:, 1], boxes.center[:, 0])
    rel = np.angle(np.exp(1j * (np.arctan2(corners[..., 1], corners[..., 0]) - centre_az[:, None])))
    az_lo, az_hi = centre_az + rel.min(axis=1), centre_az + rel.max(axis=1)
    r = np.linalg.norm(boxes.center[:, :2], axis=1)
    half_diag = np.linalg.norm(boxes.size[:, :2], axis=1) / 2
    outside = r > half_diag + 0.1
    d_min = np.maximum(r - half_diag, 0.1)
    d_max = r + half_diag
    top = boxes.center[:, 2] + boxes.size[:, 2] / 2
    bottom = boxes.center[:, 2] - boxes.size[:, 2] / 2
    el_hi = np.arctan2(top, np.where(top > 0, d_min, d_max))
    el_lo = np.arctan2(bottom, np.where(bottom < 0, d_min, d_max))
    return az_lo, az_hi, el_lo, el_hi, outside


def _rays_towards(xyz: np.ndarray, az_lo, az_hi, el_lo, el_hi, judged) -> tuple[np.ndarray, np.ndarray]:
    """(point, box) pairs whose ray from the sensor lies in the box's angular window.

    One pass over the scan (the azimuth of each point in the scan's precision, a radix sort
    into 0.1 deg bins); the boxes' bins expand into candidate pairs without a Python loop;
    elevations are computed for the candidates only. Non-finite points never pair."""
    az = np.arctan2(xyz[:, 1], xyz[:, 0])
    with np.errstate(invalid="ignore"):
        scaled = (az + np.float32(np.pi)) * np.float32(_AZ_BINS / (2 * np.pi))
        key = np.where(np.isfinite(scaled), scaled, 0).astype(np.int16)
    np.clip(key, 0, _AZ_BINS - 1, out=key)
    order = np.argsort(key, kind="stable")
    starts = np.searchsorted(key[order], np.arange(_AZ_BINS + 1))
    boxes_idx = np.flatnonzero(judged)
    b0 = np.floor((az_lo[boxes_idx] + np.pi) * (_AZ_BINS / (2 * np.pi))).astype(np.int64)
    b1 = np.floor((az_hi[boxes_idx] + np.pi) * (_AZ_BINS / (2 * np.pi))).astype(np.int64)
    nbins = b1 - b0 + 1
    box_of_bin = np.repeat(boxes_idx, nbins)
    local = np.arange(nbins.sum()) - np.repeat(np.cumsum(nbins) - nbins, nbins)
    bins = (np.repeat(b0, nbins) + local) % _AZ_BINS
    lo, hi = starts[bins], starts[bins + 1]
    count = hi - lo
    pair_box = np.repeat(box_of_bin, count)
    offset = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
    pair_point = order[np.repeat(lo, count) + offset]
    p = xyz[pair_point].astype(np.float64)
    with np.errstate(invalid="ignore"):
        e = np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1]))
        keep = (e >= el_lo[pair_box]) & (e <= el_hi[pair_box])
    return pair_point[keep], pair_box[keep]


def _expected_beams(boxes: Boxes, sensor: SensorModel, az_lo, az_hi, el_lo, el_hi, judged) -> np.ndarray:
    """Beams of the sensor model (rings x azimuth steps) whose rays hit each box."""
    out = np.zeros(len(boxes))
    rings = sensor.ring_elevations()
    step = np.deg2rad(sensor.azimuth_resolution_deg)
    idx = np.flatnonzero(judged)
    if not len(idx):
        return out
    n_az_full = np.floor((az_hi[idx] - az_lo[idx]) / step).astype(np.int64) + 1
    # A near box spans hundreds of columns: sample at most EXPECTED_COLUMNS of them, evenly,
    # and scale the count back (an unbiased estimate; exact for far boxes).
    n_az = np.minimum(n_az_full, EXPECTED_COLUMNS)
    stretch = n_az_full / n_az
    r_lo = np.searchsorted(rings, el_lo[idx])
    r_hi = np.searchsorted(rings, el_hi[idx], side="right")
    n_ring = np.maximum(r_hi - r_lo, 0)
    per = n_az * n_ring
    box = np.repeat(idx, per)
    local = np.arange(per.sum()) - np.repeat(np.cumsum(per) - per, per)
    n_az_b = np.repeat(n_az, per)
    azimuth = np.repeat(az_lo[idx], per) + (local % n_az_b + 0.5) * step * np.repeat(stretch, per)
    elevation = rings[np.repeat(r_lo, per) + local // n_az_b]
    direction = np.stack(
        [np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)], axis=1
    )
    origin = _box_frame(boxes, box, np.zeros((len(box), 3)))
    c, s = np.cos(boxes.yaw[box]), np.sin(boxes.yaw[box])
    dx, dy = direction[:, 0], direction[:, 1]
    d_local = np.stack([c * dx + s * dy, -s * dx + c * dy, direction[:, 2]], 1)
    half = boxes.size[box] / 2
    lo, hi = -half.copy(), half.copy()
    lo[:, 2] += EVIDENCE_GROUND
    tmin, tmax = _slab(origin, d_local, lo, hi)
    hit = tmax >= np.maximum(tmin, 0.0)
    weight = np.zeros(len(boxes))
    weight[idx] = stretch
    out += np.bincount(box[hit], minlength=len(boxes)) * weight
    return out


def _local_ground(points: np.ndarray, boxes: Boxes, reach: float | np.ndarray = GROUND_REACH,
                  quantile: float = 0.05) -> np.ndarray:
    """Ground height around each box: the ``quantile`` of the z of the returns within ``reach``
    metres of its footprint and from 3 m below to 1 m above its bottom (NaN when there are none)."""
    n = len(boxes)
    if n == 0:
        return np.zeros(0)
    bottom = boxes.center[:, 2] - boxes.size[:, 2] / 2
    centre = np.c_[boxes.center[:, :2], bottom - 1.0]
    wide = Boxes(centre, np.c_[boxes.size[:, :2] + 2 * np.reshape(reach, (-1, 1)), np.full(n, 4.0)], boxes.yaw)
    z = np.asarray(points)[:, 2]
    out = np.full(n, np.nan)
    for b, idx in enumerate(points_in_boxes(points, wide)):  # one partial sort per box (boxes, not points)
        if len(idx):
            k = int(quantile * (len(idx) - 1))
            out[b] = np.partition(z[idx], k)[k]
    return out


def evidence(points: np.ndarray, boxes: Boxes, sensor: SensorModel | None = None,
             reach: float | np.ndarray | None = None, columns: bool = False) -> Evidence:
    """Free-space, return-count and ground-contact measurements of every box, from the scan.

    ``reach``: metres around each footprint the local ground looks. Default: the shipped
    filter's (:func:`pcc_ros.pipeline.evidence.ground_reach`, widened by the beam model's ring
    spacing), not 93cd59e's fixed ``GROUND_REACH``: the comparisons measure 93cd59e's
    algorithm computing the same quantity as the shipped code, so its outputs are checked
    bit for bit against the shipped filter's.

    The sensor sits at the scan frame's origin (true for a scan in its own sensor frame).
    Vectorised over (ray, box) pairs: one pass over the scan, no loop over points or boxes.
    """
    sensor = sensor or SensorModel()
    points = np.asarray(points)
    n = len(boxes)
    zero = np.zeros(n)
    if n == 0:
        return Evidence(*([zero] * 7), _derive(*([zero] * 7), boxes))
    if points.ndim != 2 or points.shape[1] < 3:
        raise DataError(f"points must be (N, >=3), got shape {points.shape}")
    az_lo, az_hi, el_lo, el_hi, judged = _angular_window(boxes)
    xyz = points[:, :3]
    pair_point, pair_box = _rays_towards(xyz, az_lo, az_hi, el_lo, el_hi, judged)
    # Box-frame ray: origin (the sensor, one per box) + t * (point - origin); t = 1 at the return.
    origin_box = _box_frame(boxes, np.arange(n), np.zeros((n, 3)))
    o_local = origin_box[pair_box]
    direction = _box_frame(boxes, pair_box, xyz[pair_point].astype(np.float64)) - o_local
    half = boxes.size / 2
    body_lo, body_hi = -half.copy(), half.copy()
    body_lo[:, 2] += EVIDENCE_GROUND
    tin, tout = _slab(o_local, direction, body_lo[pair_box], body_hi[pair_box])
    through = np.flatnonzero(tout >= np.maximum(tin, 0.0))  # rays that cross the box at all
    pair_point, pair_box = pair_point[through], pair_box[through]
    o_local, direction = o_local[through], direction[through]
    tin, tout = tin[through], tout[through]
    # the shipped core (the band, or the cabin where no ring of the beam model crosses it)
    core_lo, core_hi = core_box(boxes, sensor)
    cin, cout = _slab(o_local, direction, core_lo[pair_box], core_hi[pair_box])
    through_core = cout >= np.maximum(cin, 0.0)
    inside = (tin <= 1.0) & (1.0 <= tout)
    occluded = 1.0 < tin
    stop = through_core & (tin <= 1.0) & (1.0 <= cout)
    passed = through_core & (1.0 > cout)

    def count(mask):
        return np.bincount(pair_box[mask], minlength=n).astype(np.float64)

    n_in, n_occ, n_stop = count(inside), count(occluded), count(stop)
    n_pass, n_rays = count(passed), np.bincount(pair_box, minlength=n).astype(np.float64)
    expected = _expected_beams(boxes, sensor, az_lo, az_hi, el_lo, el_hi, judged)
    ground = _local_ground(xyz, boxes, ground_reach(boxes, sensor) if reach is None else reach)
    terms = _derive(n_in, n_stop, n_pass, n_occ, n_rays, expected, ground, boxes)
    if columns:
        n_filled, n_seen = _azimuth_columns(points, boxes, sensor, pair_point, pair_box, inside, passed)
        terms = {**terms, "n_filled": n_filled, "n_seen": n_seen, "cover": cover(n_filled, n_seen)}
    return Evidence(n_in, n_stop, n_pass, n_occ, n_rays, expected, ground, terms)


def _azimuth_columns(points, boxes: Boxes, sensor: SensorModel, pair_point, pair_box, inside, passed):
    """``cover``'s columns from this pass's (ray, box) pairs, vectorised: each marked pair's column
    on the shipped grid (:func:`pcc_ros.pipeline.evidence._column_grid` over the shipped angular
    window, the beam model's azimuth step), then the distinct (box, column) keys holding an
    in-box return (filled) and those holding one or a ray through the core (seen)."""
    n = len(boxes)
    window = angular_window(boxes)
    judged = np.flatnonzero(window[4])
    col_lo, col_scale, col_count = (np.zeros(n), np.ones(n), np.ones(n, dtype=np.int64))
    col_lo[judged], col_scale[judged], col_count[judged] = _column_grid(
        window, judged, np.deg2rad(sensor.azimuth_resolution_deg))
    x, y, _ = _columns(points)
    with np.errstate(invalid="ignore"):
        azimuth = np.arctan2(y, x).astype(np.float64)  # the scan's precision, as the kernel reads it
    mark = inside | passed
    box, a = pair_box[mark], azimuth[pair_point[mark]] - col_lo[pair_box[mark]]
    a -= 2 * np.pi * np.floor((a + np.pi) / (2 * np.pi))
    col = np.clip(np.floor(a * col_scale[box]).astype(np.int64), 0, col_count[box] - 1)
    key = box * (int(col_count.max()) + 1) + col

    def distinct(keys):
        return np.bincount(np.unique(keys) // (int(col_count.max()) + 1), minlength=n).astype(np.float64)

    return distinct(key[inside[mark]]), distinct(key)
