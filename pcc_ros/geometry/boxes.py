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

import itertools

import numpy as np

from pcc_ros.errors import DataError
from pcc_ros.geometry.segments import positions_in_runs
from pcc_ros.scratch import Scratch
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
_PAIR_CHUNK = 16384  # candidate pairs tested at a time


def _bev_corners(boxes: Boxes) -> np.ndarray:
    """``(N, 4, 2)`` bird's-eye-view corners, counter-clockwise."""
    return box_corners(boxes)[:, :4, :2]


def round_up_to(values: np.ndarray, dt: type) -> np.ndarray:
    """Smallest ``dt`` numbers >= ``values`` (so ``p >= bound`` is exact for ``dt`` points)."""
    out = values.astype(dt)
    return np.where(out < values, np.nextafter(out, dt(np.inf)), out)


def round_down_to(values: np.ndarray, dt: type) -> np.ndarray:
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


_SCRATCH = Scratch()  # the scan-sized temporaries of BoxCandidates (pcc_ros.scratch); never returned


class BoxCandidates:
    """One pass of a scan against a set of boxes: the points each box may contain.

    The pass hashes every point into a bird's-eye-view grid over the (margin-enlarged)
    boxes and looks its cell up in a small table of the cells each box can reach (the
    cells of its footprint's bounding rectangle, widened by one, minus those a yawed box
    cannot touch). What the pass leaves is a short list: the points in such cells, with
    their cell. From it:

    * :attr:`pairs_per_box` -- the (point, box) candidate pairs of each box, an upper bound
      of the points it contains, known before any pair is formed (the pipeline's work bound);
    * :meth:`pairs` -- the exact test on the candidates of all boxes or of a subset: the
      pairs inside, grouped by box (ascending), points ascending within a box, and
      optionally the points' box-frame coordinates.

    Cost: one compiled pass over the scan (:mod:`pcc_ros.geometry.box_kernels`; the cell in
    float32), then work proportional to the candidates. The
    exact test runs in the scan's precision (float32 sensor data stays float32) with the
    z bounds rounded outward-exactly, so it agrees with an exact float64 test. NaN points
    fall in the grid's empty border: never candidates, never inside.

    Args:
        points: ``(N, >=3)`` scan (x, y, z first), any float dtype.
        boxes: the boxes, in the scan's frame.
        margin: metres added to every side of each box.
        ground_margin: points less than this many metres above the bottom of the
            (margin-enlarged) box are not inside.
        cell: BEV cell in metres (default: a quarter of the median box width); speed only.

    Raises:
        DataError: points of the wrong shape, or a box with NaN pose / non-positive size.
    """

    def __init__(self, points: np.ndarray, boxes: Boxes, margin: float = 0.0, ground_margin: float = 0.0,
                 cell: float | None = None) -> None:
        pts = np.asarray(points)
        if pts.ndim != 2 or pts.shape[1] < 3:
            raise DataError(f"points must be (N, >=3), got shape {pts.shape}")
        _check_boxes(boxes)
        self.points, self.boxes = pts, boxes
        self.margin, self.ground_margin = float(margin), float(ground_margin)
        nb = len(boxes)
        self._hit = np.zeros(0, np.int64)
        self._entry_row = self._entry_box = np.zeros(0, np.int64)
        self._n_rows = 0
        self.pairs_per_box = np.zeros(nb, dtype=np.int64)
        self._dt = dt = np.float32 if pts.dtype == np.float32 else np.float64
        if nb == 0 or len(pts) == 0:
            self._hit_row = np.zeros(0, np.int64)
            return
        # The test runs in the scan's precision (float32 for sensor data); the z bounds are
        # rounded outward-exactly to it, so the bottom / top tests (where the ground returns
        # sit, right at the boundary) agree with an exact float64 test.
        half_z = boxes.size[:, 2] / 2.0
        self._zlo = round_up_to(boxes.center[:, 2] - half_z - self.margin + self.ground_margin, dt)
        self._zhi = round_down_to(boxes.center[:, 2] + half_z + self.margin, dt)
        grid, key, n_rows, row_dtype = self._table(boxes, self.margin, _cell_size(boxes, cell))
        self._scan(pts, grid, key, n_rows, row_dtype)
        per_row = np.bincount(self._hit_row, minlength=n_rows + 1)
        self.pairs_per_box = np.bincount(self._entry_box, weights=np.take(per_row, self._entry_row),
                                         minlength=nb).astype(np.int64)

    def _table(self, boxes: Boxes, margin: float, cell: float):
        """The grid over the boxes and its (cell, box) entries, grouped by cell (rows 1..R)."""
        cos, sin = np.cos(boxes.yaw), np.sin(boxes.yaw)
        hl = boxes.size[:, 0] * 0.5 + margin
        hw = boxes.size[:, 1] * 0.5 + margin
        # half extents of the bounding rectangle of each margin-enlarged, yawed footprint
        ex = np.abs(cos) * hl + np.abs(sin) * hw
        ey = np.abs(sin) * hl + np.abs(cos) * hw
        cx, cy = boxes.center[:, 0], boxes.center[:, 1]
        lox, hix, loy, hiy = cx - ex, cx + ex, cy - ey, cy + ey
        x0, y0 = float(lox.min()), float(loy.min())
        width, height = float(hix.max()) - x0, float(hiy.max()) - y0
        nx, ny = int(width // cell) + 1, int(height // cell) + 1
        if nx * ny > 1_000_000:  # boxes spread very far apart: coarser cells
            cell *= float(np.sqrt(nx * ny / 1_000_000.0)) * 1.01
            nx, ny = int(width // cell) + 1, int(height // cell) + 1
        # One empty cell of border on every side: points off the grid (and NaN) land there.
        nx, ny = nx + 2, ny + 2
        ox, oy = x0 - cell, y0 - cell
        # Each box's cell range, widened by one cell each way (a point on a cell boundary
        # may round into either cell), kept off the border.
        ix0 = np.maximum(np.floor((lox - ox) / cell).astype(np.int64) - 1, 1)
        ix1 = np.minimum(np.floor((hix - ox) / cell).astype(np.int64) + 1, nx - 2)
        iy0 = np.maximum(np.floor((loy - oy) / cell).astype(np.int64) - 1, 1)
        iy1 = np.minimum(np.floor((hiy - oy) / cell).astype(np.int64) + 1, ny - 2)
        # Keep the cells that can touch the rotated box: the cell centre within the enlarged
        # box grown by half a cell diagonal (and a hair for rounding), which trims the corners
        # of the bounding rectangle that a yawed box leaves empty. Column by column: the centres
        # of a column inside that rectangle are one run of cells, from two slab intervals.
        reach = cell * np.sqrt(0.5) * 1.001
        n_col = ix1 - ix0 + 1
        col_box = np.repeat(np.arange(len(boxes)), n_col)
        gx = np.repeat(ix0, n_col) + positions_in_runs(n_col)
        dx = (gx + 0.5) * cell - np.take(cx - ox, col_box)  # column centre, box-relative
        c, s = np.take(cos, col_box), np.take(sin, col_box)
        # |c dx + s dy| <= hl + reach  and  |c dy - s dx| <= hw + reach,  dy = y - centre y
        lo, hi = np.full(len(gx), -np.inf), np.full(len(gx), np.inf)
        for k, bound, shift in ((s, hl + reach, c * dx), (c, hw + reach, -s * dx)):
            b = np.take(bound, col_box)
            with np.errstate(divide="ignore", invalid="ignore"):
                t1, t2 = (-b - shift) / k, (b - shift) / k
            flat = k == 0  # the constraint does not involve dy: all or nothing
            ok = np.abs(shift) <= b
            np.maximum(lo, np.where(flat, np.where(ok, -np.inf, np.inf), np.minimum(t1, t2)), out=lo)
            np.minimum(hi, np.where(flat, np.where(ok, np.inf, -np.inf), np.maximum(t1, t2)), out=hi)
        cy_cells = np.take((cy - oy) / cell - 0.5, col_box)  # centre y = (gy + 0.5) cell
        y0_col, y1_col = np.take(iy0, col_box), np.take(iy1, col_box)
        first_y = np.maximum(np.ceil(np.clip(lo / cell + cy_cells, -1.0, ny)), y0_col).astype(np.int64)
        last_y = np.minimum(np.floor(np.clip(hi / cell + cy_cells, -1.0, ny)), y1_col).astype(np.int64)
        n_cell = np.maximum(last_y - first_y + 1, 0)
        box_of = np.repeat(col_box, n_cell)
        key = np.repeat(gx * ny + first_y, n_cell) + positions_in_runs(n_cell)
        n_cells = nx * ny
        # group the entries by cell (radix sort when the cell fits 16 bits); boxes stay ascending
        order = np.argsort(key.astype(np.uint16) if n_cells <= 65536 else key, kind="stable")
        key, box_of = key[order], box_of[order]
        new = np.ones(len(key), dtype=bool)
        np.not_equal(key[1:], key[:-1], out=new[1:])
        first = np.flatnonzero(new)
        n_rows = len(first)
        row_dtype = np.int16 if n_rows < 32767 else np.int32
        row_of = np.zeros(n_cells, dtype=row_dtype)
        row_of[key[first]] = np.arange(1, n_rows + 1, dtype=row_dtype)
        self._entry_row, self._entry_box, self._n_rows = np.cumsum(new), box_of, n_rows
        return (ox, oy, cell, nx, ny), row_of, n_rows, row_dtype

    def _scan(self, pts: np.ndarray, grid: tuple, row_of: np.ndarray, n_rows: int, row_dtype: type) -> None:
        """The cell of every point (float32, clipped onto the grid) looked up in the table:
        the points in cells that some box reaches and within the boxes' union z range, and
        their rows (one compiled pass, :func:`pcc_ros.geometry.box_kernels.scan_cells`)."""
        from pcc_ros.geometry.box_kernels import scan_cells  # numba: heavy, only when a scan is met

        ox, oy, cell, nx, ny = grid
        n = len(pts)
        if pts.dtype not in (np.float32, np.float64):
            pts = pts.astype(np.float64)
        hit, rows = _SCRATCH("hit_index", n, np.int64), _SCRATCH("row", n, row_dtype)
        zmin, zmax = self._zlo.min(), self._zhi.max()
        m = scan_cells(pts, np.float32(ox), np.float32(oy), np.float32(1.0 / cell), nx, ny, row_of,
                       zmin, zmax, hit, rows)
        self._hit, self._hit_row = hit[:m].copy(), rows[:m].copy()

    def pairs(self, keep: np.ndarray | None = None, local: bool = False):
        """The (point, box) pairs with the point inside the box, for every box or for the boxes
        ``keep`` (a boolean mask or indices) selects: ``(pair_point, box_starts, xyz)``.

        ``pair_point`` (int64) is grouped by box, boxes in ascending order, points ascending
        within a box; box ``b``'s points are ``pair_point[box_starts[b]:box_starts[b + 1]]``
        (empty for a box not selected). ``xyz`` (with ``local``): the points' coordinates in
        their box's frame (origin at its centre, x along its heading; metres, the scan's
        precision) as three columns, else ``None``."""
        nb = len(self.boxes)
        pp, pb = self._candidates(keep)
        if len(pp) == 0:
            empty = np.zeros(0, dtype=self.points.dtype if self.points.dtype == np.float64 else np.float32)
            return np.zeros(0, np.int64), np.zeros(nb + 1, np.int64), (empty, empty, empty) if local else None
        # Box-major (a stable radix sort keeps the points ascending within a box): the boxes'
        # values then expand by np.repeat instead of a gather per pair.
        if nb > 1:
            order = np.argsort(pb, kind="stable")  # uint8 / uint16 boxes: a radix sort
            pp = np.take(pp, order)
        count = np.bincount(pb, minlength=nb)
        pts, dt = self.points, self._dt
        if not pts.flags.c_contiguous:  # np.take would copy the whole array for every chunk
            pts = np.ascontiguousarray(pts[:, :3])
        boxes = self.boxes
        values = self._box_values()
        # In chunks of pairs, every temporary in this thread's work arrays: they stay in cache
        # and mapped (a fresh array of this size is page-faulted in afresh on every frame).
        ends = np.cumsum(count).tolist()
        box_of = np.repeat(np.arange(nb, dtype=pb.dtype), count)
        size = min(len(pp), _PAIR_CHUNK)
        index = _SCRATCH("pair_box", size, np.intp)
        rows = _SCRATCH("pair_values", 8 * size, dt).reshape(size, 8)
        xyz = _SCRATCH("pair_points", size * pts.shape[1], pts.dtype).reshape(size, pts.shape[1])
        dx, dy, lx, ly, tmp = (_SCRATCH(f"pair_{k}", size, dt) for k in range(5))
        inside, test = _SCRATCH("pair_inside", size, bool), _SCRATCH("pair_test", size, bool)
        kept_parts, local_parts = [], []
        for lo in range(0, len(pp), _PAIR_CHUNK):
            hi = min(lo + _PAIR_CHUNK, len(pp))
            c = hi - lo
            if c < size:
                index, rows, xyz = index[:c], rows[:c], xyz[:c]
                dx, dy, lx, ly, tmp, inside, test = (a[:c] for a in (dx, dy, lx, ly, tmp, inside, test))
            np.copyto(index, box_of[lo:hi])
            np.take(values, index, axis=0, out=rows)  # one gather of each pair's box row
            v = rows.T
            np.take(pts, pp[lo:hi], axis=0, out=xyz)
            x, y, z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
            np.greater_equal(z, v[0], out=inside)
            inside &= np.less_equal(z, v[1], out=test)
            # box frame as canonical.to_box_local: (cos dx + sin dy, cos dy - sin dx), same roundings
            np.subtract(x, v[2], out=dx)
            np.subtract(y, v[3], out=dy)
            np.multiply(v[4], dx, out=lx)
            lx += np.multiply(v[5], dy, out=tmp)
            np.multiply(v[4], dy, out=ly)
            ly -= np.multiply(v[5], dx, out=tmp)
            inside &= np.less_equal(np.abs(lx, out=tmp), v[6], out=test)
            inside &= np.less_equal(np.abs(ly, out=tmp), v[7], out=test)
            kept = np.flatnonzero(inside)
            kept_parts.append(kept + lo)
            if local:
                local_parts.append((np.take(lx, kept), np.take(ly, kept), np.take(z, kept).astype(dt, copy=False)))
        kept = np.concatenate(kept_parts)
        starts = np.zeros(nb + 1, dtype=np.int64)
        starts[1:] = np.searchsorted(kept, ends)
        if not local:
            return np.take(pp, kept), starts, None
        lx, ly, dz = (np.concatenate(c) for c in zip(*local_parts))
        dz -= np.repeat(boxes.center[:, 2].astype(dt), np.diff(starts))
        return np.take(pp, kept), starts, (lx, ly, dz)

    def _box_values(self) -> np.ndarray:
        """Per box, the exact test's row in the test's precision: ``(zlo, zhi, cx, cy, cos, sin,
        half length + margin, half width + margin)``."""
        boxes, margin = self.boxes, self.margin
        half = boxes.size / 2.0
        return np.stack([
            self._zlo, self._zhi, boxes.center[:, 0], boxes.center[:, 1], np.cos(boxes.yaw), np.sin(boxes.yaw),
            half[:, 0] + margin, half[:, 1] + margin,
        ], axis=1).astype(self._dt)

    def _candidates(self, keep: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """(point, box) candidate pairs in point order: each point meets the boxes of its cell."""
        entry_row, entry_box, hit, hit_row = self._entry_row, self._entry_box, self._hit, self._hit_row
        if keep is not None:
            wanted = np.zeros(len(self.boxes), dtype=bool)
            wanted[keep] = True
            sel = np.take(wanted, entry_box)
            entry_row, entry_box = entry_row[sel], entry_box[sel]
        if len(entry_row) == 0 or len(hit) == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        n_rows = self._n_rows
        per_row = np.bincount(entry_row, minlength=n_rows + 1)  # boxes per row (0 for row 0)
        most = int(per_row.max())
        # box ids in the narrowest type, the largest value marking "no box": radix sorts later
        box_dtype = next(t for t in (np.uint8, np.uint16, np.uint32) if len(self.boxes) < np.iinfo(t).max)
        none = np.iinfo(box_dtype).max
        if most == 1:  # no cell shared by two boxes: one gather
            box_of_row = np.full(n_rows + 1, none, dtype=box_dtype)
            box_of_row[entry_row] = entry_box
            pb = np.take(box_of_row, hit_row)
            if keep is None:  # every row holds a box
                return hit, pb
            sel = np.flatnonzero(pb != none)
            return np.take(hit, sel), np.take(pb, sel)
        first = np.cumsum(per_row) - per_row  # entries are grouped by row
        if most > 64:  # many boxes share cells: a CSR walk without a Python loop
            n = np.take(per_row, hit_row)
            pp = np.repeat(hit, n)
            ends = np.cumsum(n)
            walk = np.repeat(np.take(first, hit_row) - ends + n, n) + np.arange(len(pp))
            return pp, np.take(entry_box.astype(box_dtype), walk)
        # A padded (row, slot) -> box table; each point gathers its row, the filled slots are
        # its pairs. In chunks of points, the gathered rows in this thread's work arrays.
        width = 1 << (most - 1).bit_length()
        shift = width.bit_length() - 1
        padded = np.full((n_rows + 1, width), none, dtype=box_dtype)
        padded[entry_row, np.arange(len(entry_row)) - np.take(first, entry_row)] = entry_box
        step = max(1, 4 * _PAIR_CHUNK // width)
        gathered = _SCRATCH("cand_rows", min(step, len(hit)) * width, box_dtype).reshape(-1, width)
        filled_mask = _SCRATCH("cand_filled", min(step, len(hit)) * width, bool)
        points, boxes = [], []
        for lo in range(0, len(hit), step):
            rows = hit_row[lo:lo + step]
            block = np.take(padded, rows, axis=0, out=gathered[:len(rows)]).reshape(-1)
            filled = np.flatnonzero(np.not_equal(block, none, out=filled_mask[:len(block)]))
            points.append(np.take(hit[lo:lo + step], filled >> shift))
            boxes.append(np.take(block, filled))
        if len(points) == 1:
            return points[0], boxes[0]
        return np.concatenate(points), np.concatenate(boxes)


def warm_up() -> None:
    """Compile :class:`BoxCandidates`' scan pass for both scan precisions (numba, on first use;
    loaded from its disk cache after the first run on a machine), so a node's first frame does
    not pay for it. Idempotent and cheap once done."""
    boxes = Boxes(np.array([[10.0, 0.0, -0.8]]), np.array([[4.0, 1.8, 1.5]]), np.zeros(1))
    scan = np.array([[10.0, 0.0, -0.8], [0.0, 0.0, 0.0]])
    for dtype in (np.float32, np.float64):
        BoxCandidates(scan.astype(dtype), boxes)


def _pairs_in_boxes(points, boxes, margin, ground_margin, cell, local=True):
    """Pairs inside (grouped by box), box starts, and optionally box-frame coordinates."""
    return BoxCandidates(points, boxes, margin, ground_margin, cell).pairs(local=local)


def _split(values: np.ndarray, starts: np.ndarray) -> list[np.ndarray]:
    bounds = starts.tolist()  # plain slices: np.split costs ~10 us per piece
    return [values[a:b] for a, b in itertools.pairwise(bounds)]


def pairs_in_boxes(
    points: np.ndarray, boxes: Boxes, margin: float = 0.0, ground_margin: float = 0.0, cell: float | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Every (point index, box index) pair with the point inside the box, grouped by box
    (boxes ascending, points ascending within a box): :func:`points_in_boxes` without the
    split per box (for per-box reductions with ``np.bincount``, ``np.add.reduceat`` and the
    like). Same arguments and errors."""
    pair_point, starts, _ = _pairs_in_boxes(points, boxes, margin, ground_margin, cell, local=False)
    return pair_point, np.repeat(np.arange(len(boxes)), np.diff(starts))


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
    if len(boxes) == 0:
        BoxCandidates(points, boxes)  # the same checks
        return []
    pair_point, starts, _ = _pairs_in_boxes(points, boxes, margin, ground_margin, cell, local=False)
    return _split(pair_point, starts)


def canonical_crops(candidates: BoxCandidates, keep: np.ndarray | None = None
                    ) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """:func:`crop_canonical` from a :class:`BoxCandidates` pass (all boxes, or those ``keep``
    selects; the others get empty crops)."""
    boxes = candidates.boxes
    if len(boxes) == 0:
        return [], []
    pair_point, starts, (lx, ly, dz) = candidates.pairs(keep, local=True)
    length = np.repeat(boxes.size[:, 0], np.diff(starts))
    canonical = np.empty((len(pair_point), 3), dtype=np.float32)
    for k, column in enumerate((lx, ly, dz)):  # float64 division, then float32 (as to_canonical)
        np.divide(column, length, out=canonical[:, k], casting="same_kind")
    return _split(pair_point, starts), _split(canonical, starts)


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
    return canonical_crops(BoxCandidates(points, boxes, margin, ground_margin, cell))


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
    ia, ib = np.nonzero(circles_meet(a, b))  # only these pairs can intersect
    out[ia, ib] = polygon_intersection_area(ca[ia], cb[ib])
    return out


def circles_meet(a: Boxes, b: Boxes) -> np.ndarray:
    """``(len(a), len(b))``: whether the circumscribed BEV circles of two boxes meet (only such
    pairs can intersect: the BEV overlaps clip the polygons of those only)."""
    ra = np.linalg.norm(a.size[:, :2], axis=1) / 2.0
    rb = np.linalg.norm(b.size[:, :2], axis=1) / 2.0
    dist = np.linalg.norm(a.center[:, None, :2] - b.center[None, :, :2], axis=2)
    return dist <= ra[:, None] + rb[None, :]


def iou_bev_pairs(boxes: Boxes, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """BEV IoU of the pairs ``(boxes[i[k]], boxes[j[k]])``: the entries ``[i, j]`` of
    ``iou_bev(boxes, boxes)`` for pairs whose circles meet (:func:`circles_meet`), bit for bit,
    without clipping the polygons of every other pair (a frame's boxes rarely meet)."""
    corners = _bev_corners(boxes)
    inter = polygon_intersection_area(corners[i], corners[j])
    area = boxes.size[:, 0] * boxes.size[:, 1]
    union = area[i] + area[j] - inter
    return inter / np.maximum(union, 1e-12)


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
