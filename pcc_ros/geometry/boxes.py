"""Box geometry: corners, points-in-boxes (one vectorised pass), crops, rotated IoU.

Everything here works on :class:`pcc_ros.types.Boxes` (struct of arrays) so a frame's
boxes are processed together. The points-in-boxes test is the hot path of both nodes:
it runs on every 120k-point scan, so it avoids touching the whole scan once per box.
Instead one pass over the scan hashes every point into a coarse bird's-eye-view grid
that only covers the boxes; a table built from the (few) boxes says which boxes
overlap each cell; only points in such cells become (point, box) candidate pairs,
and the exact rotated test runs on those pairs.
"""

from __future__ import annotations

import numpy as np

from pcc_ros.errors import DataError
from pcc_ros.geometry.canonical import to_box_local
from pcc_ros.types import Boxes

# Unit-cube corner signs in the order :func:`box_corners` documents.
_CORNER_SIGNS = np.array(
    [
        [1, 1, -1], [-1, 1, -1], [-1, -1, -1], [1, -1, -1],
        [1, 1, 1], [-1, 1, 1], [-1, -1, 1], [1, -1, 1],
    ],
    dtype=np.float64,
)


def box_corners(boxes: Boxes) -> np.ndarray:
    """``(N, 8, 3)`` corners of every box: the package's one corner function.

    Order — bottom face first, counter-clockwise seen from above starting at front-left,
    then the top face in the same order (corner ``k + 4`` sits above corner ``k``)::

        seen from above, box frame          +y (left)
                                              ^
            1 rear-left  ---------  0 front-left
            |                       |         --> +x (heading, front)
            2 rear-right ---------  3 front-right

    so ``[:, :4, :2]`` is the counter-clockwise bird's-eye-view footprint.
    """
    half = boxes.size[:, None, :] / 2.0 * _CORNER_SIGNS[None]
    c, s = np.cos(boxes.yaw)[:, None], np.sin(boxes.yaw)[:, None]
    x = c * half[..., 0] - s * half[..., 1]
    y = s * half[..., 0] + c * half[..., 1]
    return np.stack([x, y, half[..., 2]], axis=-1) + boxes.center[:, None, :]


CELL_FRACTION = 0.25  # default BEV hash cell as a fraction of the median box width


def _bev_corners(boxes: Boxes) -> np.ndarray:
    """``(N, 4, 2)`` bird's-eye-view corners, counter-clockwise."""
    return box_corners(boxes)[:, :4, :2]


def _round_up(values: np.ndarray, dt: type) -> np.ndarray:
    """Smallest ``dt`` numbers >= ``values`` (so ``p >= bound`` is exact for ``dt`` points)."""
    out = values.astype(dt)
    return np.where(out < values, np.nextafter(out, dt(np.inf)), out)


def _round_down(values: np.ndarray, dt: type) -> np.ndarray:
    """Largest ``dt`` numbers <= ``values``."""
    out = values.astype(dt)
    return np.where(out > values, np.nextafter(out, dt(-np.inf)), out)


def _check_boxes(boxes: Boxes) -> None:
    if len(boxes) and not boxes.valid_mask().all():
        boxes.validate()


def _cell_size(boxes: Boxes, cell: float | None) -> float:
    if cell is None:
        # Cells about a quarter of a car's width keep the table small and the candidate
        # overhead (points in cells but outside boxes) low.
        cell = float(np.clip(CELL_FRACTION * np.median(np.minimum(boxes.size[:, 0], boxes.size[:, 1])), 0.25, 4.0))
    return float(cell)


def _candidate_pairs(
    xy: np.ndarray, boxes: Boxes, margin: float, cell: float | None, z: np.ndarray | None = None,
    z_range: tuple[float, float] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """(point index, box index) pairs whose BEV grid cell may overlap the box (a superset of
    the pairs inside), in point order. With ``z`` and ``z_range`` (the union of the boxes'
    height ranges), points outside that range never become candidates.

    Cost: a handful of contiguous float32 passes over the scan, then work proportional to
    the points on the boxes' grid (a lookup in a small uint8 cell table) and to the
    candidates; boxes are only touched to build the cell -> boxes table.
    """
    # (B, 2) axis-aligned BEV extents of the margin-enlarged boxes (their corners: a yawed
    # box grown by ``margin`` reaches further than its corners' extent plus ``margin``)
    corners = _bev_corners(Boxes(boxes.center, boxes.size + 2.0 * margin, boxes.yaw))
    lo, hi = corners.min(axis=1), corners.max(axis=1)
    cell = _cell_size(boxes, cell)
    origin = lo.min(axis=0)
    n_cells = np.floor((hi.max(axis=0) - origin) / cell).astype(np.int64) + 1
    if n_cells[0] * n_cells[1] > 1_000_000:  # boxes spread very far apart: coarser cells
        cell *= float(np.sqrt(n_cells[0] * n_cells[1] / 1_000_000.0)) * 1.01
        n_cells = np.floor((hi.max(axis=0) - origin) / cell).astype(np.int64) + 1
    # The grid has a border of one empty cell on every side (the widened cell ranges below).
    nx, ny = int(n_cells[0]) + 2, int(n_cells[1]) + 2
    origin = origin - cell

    # Cell -> boxes table in CSR form (loops over boxes are replaced by repeat/arange). The
    # cell range of each box is widened by one cell each way and the touch test below by a
    # hair, so a point on a cell boundary (float32 rounding) still finds its boxes.
    c0 = np.floor((lo - origin) / cell).astype(np.int64) - 1
    c1 = np.floor((hi - origin) / cell).astype(np.int64) + 1
    span = c1 - c0 + 1  # (B, 2)
    per_box = span[:, 0] * span[:, 1]
    box_of = np.repeat(np.arange(len(boxes)), per_box)
    local = np.arange(per_box.sum()) - np.repeat(np.cumsum(per_box) - per_box, per_box)
    cx = c0[box_of, 0] + local // span[box_of, 1]
    cy = c0[box_of, 1] + local % span[box_of, 1]
    # Keep only the cells that can touch the rotated box: the cell centre within the
    # (margin-enlarged) box grown by half a cell diagonal. Trims the AABB corners that a
    # yawed box leaves empty, which would otherwise become candidate points.
    ccx, ccy, _ = to_box_local(origin[0] + (cx + 0.5) * cell, origin[1] + (cy + 0.5) * cell, 0.0,
                               boxes.center[box_of, 0], boxes.center[box_of, 1], 0.0,
                               np.cos(boxes.yaw[box_of]), np.sin(boxes.yaw[box_of]))
    reach = cell * np.sqrt(0.5) * 1.001 + margin
    touch = (np.abs(ccx) <= boxes.size[box_of, 0] / 2 + reach) & (np.abs(ccy) <= boxes.size[box_of, 1] / 2 + reach)
    touch &= (cx >= 1) & (cx < nx - 1) & (cy >= 1) & (cy < ny - 1)  # the border stays empty
    box_of, key = box_of[touch], cx[touch] * ny + cy[touch]
    # One pass over the scan: the cell of every point, in float32 with contiguous
    # temporaries; comparisons (NaN compares False) keep the points on the grid (and, with
    # ``z``, within the boxes' heights), and only those are touched again (np.take is several
    # times faster than fancy indexing).
    inv = np.float32(1.0 / cell)
    with np.errstate(invalid="ignore"):
        gx = np.subtract(xy[:, 0], np.float32(origin[0]), dtype=np.float32)
        gx *= inv
        gy = np.subtract(xy[:, 1], np.float32(origin[1]), dtype=np.float32)
        gy *= inv
        inside = gx >= 0
        inside &= gx < nx
        inside &= gy >= 0
        inside &= gy < ny
        if z is not None:
            inside &= z >= z_range[0]
            inside &= z <= z_range[1]
    pts = np.flatnonzero(inside)
    pkey = np.take(gx, pts).astype(np.int32)  # >= 0: truncation is the floor
    pkey *= np.int32(ny)
    pkey += np.take(gy, pts).astype(np.int32)
    return pairs_from_cells(pts, pkey, key, box_of, nx * ny)


def pairs_from_cells(
    point: np.ndarray, point_cell: np.ndarray, entry_cell: np.ndarray, entry_box: np.ndarray, n_cells: int
) -> tuple[np.ndarray, np.ndarray]:
    """Points hashed into cells meet the boxes listed per cell: every (point, box) pair with
    the box listed in the point's cell.

    Args:
        point: ``(P,)`` point indices, ascending; ``point_cell``: their cells in ``[0, n_cells)``.
        entry_cell, entry_box: ``(E,)`` the (cell, box) entries of the table, any order.

    Returns ``(pair_point, pair_box)`` in point order, boxes ascending within a point (for
    boxes listed in ascending order per cell). No Python loop: a lookup of each point's box
    count in a small table, then a padded (cell, slot) table when a cell holds a few boxes
    (one gather per candidate), or a CSR walk when it holds many.
    """
    order = np.argsort(entry_cell, kind="stable")
    cell_sorted = entry_cell[order]
    table_boxes = entry_box[order]
    counts = np.bincount(entry_cell, minlength=n_cells)
    starts = np.concatenate([[0], np.cumsum(counts)])
    most = int(counts.max(initial=0))
    counts_table = counts.astype(np.uint8 if most < 256 else np.int64)  # uint8: the lookups stay in cache
    n_per_point = np.take(counts_table, point_cell)
    hit = np.flatnonzero(n_per_point)
    pts, pkey, n_per_point = np.take(point, hit), np.take(point_cell, hit), np.take(n_per_point, hit)
    if most <= 1:  # no cell shared by two boxes: one box per point
        return pts, np.take(table_boxes, np.take(starts, pkey)).astype(np.int64)
    if most <= 8:
        # A few boxes per cell at most: a padded (occupied cell, slot) -> box table; one
        # gather of each candidate's row, the valid slots found in one pass.
        width = 1 << (most - 1).bit_length()  # a power of two: the point is a shift away
        occupied = np.flatnonzero(counts)
        row_of = np.zeros(n_cells, dtype=np.int32)
        row_of[occupied] = np.arange(len(occupied), dtype=np.int32)
        padded = np.full((len(occupied), width), -1, dtype=np.int32)
        padded[row_of[cell_sorted], np.arange(len(cell_sorted)) - starts[cell_sorted]] = table_boxes
        boxes_of = np.take(padded, np.take(row_of, pkey), axis=0).reshape(-1)
        slot = np.flatnonzero(boxes_of >= 0)
        return np.take(pts, slot >> (width.bit_length() - 1)), np.take(boxes_of, slot).astype(np.int64)
    # CSR walk without a Python loop (many boxes share cells).
    n_per_point = n_per_point.astype(np.int64)
    pair_point = np.repeat(pts, n_per_point)
    ends = np.cumsum(n_per_point)
    slot = np.repeat(np.take(starts, pkey) - ends + n_per_point, n_per_point) + np.arange(ends[-1])
    return pair_point, np.take(table_boxes, slot).astype(np.int64)


def _pairs_in_boxes(
    points: np.ndarray,
    boxes: Boxes,
    margin: float,
    ground_margin: float,
    cell: float | None,
    local: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Exact (point, box) pairs in point order, plus (``local``) the points' box-frame
    coordinates (metres, the scan's precision)."""
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] < 3:
        raise DataError(f"points must be (N, >=3), got shape {pts.shape}")
    _check_boxes(boxes)
    if len(boxes) == 0 or len(pts) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3)) if local else None
    dt = np.float32 if pts.dtype == np.float32 else np.float64
    half = boxes.size / 2.0
    zlo = _round_up(boxes.center[:, 2] - half[:, 2] - margin + ground_margin, dt)
    zhi = _round_down(boxes.center[:, 2] + half[:, 2] + margin, dt)
    pair_point, pair_box = _candidate_pairs(pts[:, :2], boxes, margin, cell, pts[:, 2], (zlo.min(), zhi.max()))
    # Per-box parameters gathered per pair with np.take; the test runs in the scan's
    # precision (float32 for sensor data) on box-relative x/y. The z bounds are rounded
    # outward-exactly to that precision, so the bottom / top tests (where the ground
    # returns sit, right at the boundary) agree with an exact float64 test.
    table = np.stack(
        [
            boxes.center[:, 0], boxes.center[:, 1], boxes.center[:, 2],
            np.cos(boxes.yaw), np.sin(boxes.yaw),
            half[:, 0] + margin, half[:, 1] + margin,
        ],
        axis=0,
    ).astype(dt)
    cx, cy, cz, c, s, hl, hw = (np.take(col, pair_box) for col in table)
    pz = np.take(pts[:, 2], pair_point).astype(dt, copy=False)
    # z first: a cheap test that drops most of the ground and everything above the boxes.
    keep = pz >= np.take(zlo, pair_box)
    keep &= pz <= np.take(zhi, pair_box)
    lx, ly, dz = to_box_local(np.take(pts[:, 0], pair_point).astype(dt, copy=False),
                              np.take(pts[:, 1], pair_point).astype(dt, copy=False), pz, cx, cy, cz, c, s)
    keep &= np.abs(lx) <= hl
    keep &= np.abs(ly) <= hw
    keep = np.flatnonzero(keep)
    if not local:
        return np.take(pair_point, keep), np.take(pair_box, keep), None
    out = np.stack([np.take(lx, keep), np.take(ly, keep), np.take(dz, keep)], axis=1)
    return np.take(pair_point, keep), np.take(pair_box, keep), out


def _group_by_box(pair_point: np.ndarray, pair_box: np.ndarray, n_boxes: int, *values: np.ndarray) -> list:
    """Split pair arrays per box; point indices stay ascending inside each box."""
    key = pair_box.astype(np.int16 if n_boxes < 32767 else np.int64)  # int16: radix sort
    order = np.argsort(key, kind="stable")
    ends = np.cumsum(np.bincount(pair_box, minlength=n_boxes)).tolist()
    starts = [0, *ends[:-1]]

    def split(a: np.ndarray) -> list[np.ndarray]:  # plain slices: np.split costs ~10 us per piece
        return [a[s:e] for s, e in zip(starts, ends)]

    out = [split(np.take(pair_point, order))]
    out.extend(split(np.take(v, order, axis=0)) for v in values)
    return out


def pairs_in_boxes(
    points: np.ndarray, boxes: Boxes, margin: float = 0.0, ground_margin: float = 0.0, cell: float | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Every (point index, box index) pair with the point inside the box, in point order:
    :func:`points_in_boxes` without the split per box (for per-box reductions with
    ``np.bincount`` and the like). Same arguments and errors."""
    pair_point, pair_box, _ = _pairs_in_boxes(points, boxes, margin, ground_margin, cell, local=False)
    return pair_point, pair_box


def points_in_boxes(
    points: np.ndarray,
    boxes: Boxes,
    margin: float = 0.0,
    ground_margin: float = 0.0,
    cell: float | None = None,
) -> list[np.ndarray]:
    """Indices (ascending, int64) of the points inside each box, in one vectorised pass.

    Args:
        points: ``(N, >=3)`` scan (x, y, z first), any float dtype; NaN rows are never inside.
        boxes: the boxes, in the scan's frame.
        margin: metres added to every side of each box (a detector's box is often tight).
        ground_margin: points lower than this many metres above the bottom of the
            (margin-enlarged) box are dropped: ground returns under a car's wheels sit
            right at the box bottom and would otherwise be completed as car body.
        cell: BEV hashing cell in metres (default: about one box width); affects speed only.

    Raises:
        DataError: points of the wrong shape, or a box with NaN pose / non-positive size.
    """
    pair_point, pair_box, _ = _pairs_in_boxes(points, boxes, margin, ground_margin, cell)
    if len(boxes) == 0:
        return []
    return _group_by_box(pair_point, pair_box, len(boxes))[0]


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


# ----------------------------------------------------------------------------- IoU


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _inside_convex(points: np.ndarray, poly: np.ndarray, eps: float = 1e-9) -> np.ndarray:
    """``points (P, K, 2)`` inside counter-clockwise ``poly (P, 4, 2)`` -> ``(P, K)``."""
    edge = np.roll(poly, -1, axis=1) - poly  # (P, 4, 2)
    rel = points[:, :, None, :] - poly[:, None, :, :]  # (P, K, 4, 2)
    return (_cross(edge[:, None], rel) >= -eps).all(axis=2)


def polygon_intersection_area(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Exact intersection areas of pairs of convex counter-clockwise quadrilaterals.

    ``a, b``: ``(P, 4, 2)``. The intersection of two convex polygons is the convex hull
    of the vertices of each inside the other and the edge-edge crossings; those
    candidates (at most 24 per pair) are ordered by angle around their mean and the
    shoelace formula gives the area, all vectorised over pairs.
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    p = len(a)
    if p == 0:
        return np.zeros(0)
    ea = np.roll(a, -1, axis=1) - a
    eb = np.roll(b, -1, axis=1) - b
    # Edge i of a against edge j of b: a_i + t ea_i = b_j + u eb_j.
    r = ea[:, :, None, :]
    s = eb[:, None, :, :]
    qp = b[:, None, :, :] - a[:, :, None, :]
    den = _cross(r, s)
    ok = np.abs(den) > 1e-12
    safe = np.where(ok, den, 1.0)
    t = _cross(qp, s) / safe
    u = _cross(qp, r) / safe
    cross_ok = ok & (t >= 0) & (t <= 1) & (u >= 0) & (u <= 1)
    crossings = (a[:, :, None, :] + t[..., None] * r).reshape(p, 16, 2)
    cand = np.concatenate([a, b, crossings], axis=1)  # (P, 24, 2)
    valid = np.concatenate([_inside_convex(a, b), _inside_convex(b, a), cross_ok.reshape(p, 16)], axis=1)
    count = valid.sum(axis=1)
    centre = (cand * valid[..., None]).sum(axis=1) / np.maximum(count, 1)[:, None]
    rel = cand - centre[:, None, :]
    angle = np.where(valid, np.arctan2(rel[..., 1], rel[..., 0]), np.inf)
    order = np.argsort(angle, axis=1)
    ordered = np.take_along_axis(rel, order[..., None], axis=1)
    valid_sorted = np.take_along_axis(valid, order, axis=1)
    # Invalid slots (sorted last) repeat the first vertex: their shoelace terms vanish.
    ordered = np.where(valid_sorted[..., None], ordered, ordered[:, :1, :])
    area = 0.5 * _cross(ordered, np.roll(ordered, -1, axis=1)).sum(axis=1)
    return np.where(count >= 3, np.abs(area), 0.0)


def _pairwise_bev_intersection(a: Boxes, b: Boxes) -> np.ndarray:
    ca, cb = _bev_corners(a), _bev_corners(b)
    na, nb = len(a), len(b)
    out = np.zeros((na, nb))
    if na == 0 or nb == 0:
        return out
    # Only pairs whose circumscribed circles meet can intersect: skip the rest.
    ra = np.linalg.norm(a.size[:, :2], axis=1) / 2.0
    rb = np.linalg.norm(b.size[:, :2], axis=1) / 2.0
    dist = np.linalg.norm(a.center[:, None, :2] - b.center[None, :, :2], axis=2)
    ia, ib = np.nonzero(dist <= ra[:, None] + rb[None, :])
    out[ia, ib] = polygon_intersection_area(ca[ia], cb[ib])
    return out


def iou_bev(a: Boxes, b: Boxes) -> np.ndarray:
    """``(len(a), len(b))`` bird's-eye-view IoU of rotated boxes (exact polygon clipping)."""
    _check_boxes(a)
    _check_boxes(b)
    inter = _pairwise_bev_intersection(a, b)
    area_a = a.size[:, 0] * a.size[:, 1]
    area_b = b.size[:, 0] * b.size[:, 1]
    union = area_a[:, None] + area_b[None, :] - inter
    return inter / np.maximum(union, 1e-12)


def iou_3d(a: Boxes, b: Boxes) -> np.ndarray:
    """``(len(a), len(b))`` 3D IoU of yaw-rotated boxes (BEV polygon area times z overlap)."""
    _check_boxes(a)
    _check_boxes(b)
    inter_bev = _pairwise_bev_intersection(a, b)
    top = np.minimum((a.center[:, 2] + a.size[:, 2] / 2)[:, None], (b.center[:, 2] + b.size[:, 2] / 2)[None, :])
    bottom = np.maximum((a.center[:, 2] - a.size[:, 2] / 2)[:, None], (b.center[:, 2] - b.size[:, 2] / 2)[None, :])
    inter = inter_bev * np.clip(top - bottom, 0.0, None)
    vol_a = np.prod(a.size, axis=1)
    vol_b = np.prod(b.size, axis=1)
    union = vol_a[:, None] + vol_b[None, :] - inter
    return inter / np.maximum(union, 1e-12)
