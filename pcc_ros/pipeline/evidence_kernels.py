"""Compiled inner loops of the evidence filter (:mod:`pcc_ros.pipeline.evidence`).

Why compiled: the measurements are a few float operations per (ray, box), (point, box) or
(beam, box) pair, tens of thousands of pairs per frame. As numpy passes over pair arrays they
cost a pass through memory per operation and a Python call per pass (5-30 us each), and two
threads cannot overlap them: the GIL hand-over (17-32 us to wake a waiting thread) is longer
than most of the calls (``docs/filter.md``). Here each pair is visited once, its values stay in
registers, and the kernels release the GIL (``nogil``), so the pipeline's second thread measures
the ground and the expected returns truly beside the rays.

The per-pair arithmetic is the numpy code's, operation for operation, in the same precision
(float64 ray geometry; the scan's precision for the ground membership test), IEEE semantics
(``error_model="numpy"``: a division by zero is an infinity, no exception; no fast-math, so no
fused multiply-adds), so the counts and heights are bit-identical to the vectorised code kept in
``benchmarks/_reference.py`` (``pcc bench filter`` checks them). The index structures (which
points a box looks at) are counting sorts over grid cells; they only pick a superset of the
points the exact tests accept, so they do not change any value.

Compiled on first use and cached on disk (:func:`pcc_ros.jit.compiled`): ``warm_up`` compiles
them for both scan precisions so a node's first frame does not pay for it.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from pcc_ros.jit import compiled

# Per-box ray counts, columns of :func:`ray_counts`' output.
IN, OCCLUDED, STOP, PASS, RAYS = range(5)
# Per-box azimuth columns, columns of :func:`ray_counts`' ``cols`` output.
FILLED, SEEN = range(2)


@njit(inline="always")
def _minimum(a, b):
    """``np.minimum``: NaN when either is NaN."""
    if a != a or b != b:
        return np.nan
    return a if a <= b else b


@njit(inline="always")
def _maximum(a, b):
    """``np.maximum``: NaN when either is NaN."""
    if a != a or b != b:
        return np.nan
    return a if a >= b else b


@njit(inline="always")
def _fmax(a, b):
    """``np.fmax``: the other value when one is NaN."""
    if a != a:
        return b
    if b != b:
        return a
    return a if a >= b else b


@njit(inline="always")
def _fmin(a, b):
    """``np.fmin``: the other value when one is NaN."""
    if a != a:
        return b
    if b != b:
        return a
    return a if a <= b else b


@njit(inline="always")
def _slab(ix, iy, iz, lo, hi, j):
    """Where the ray ``t * d`` (box frame, from the sensor; ``ix, iy, iz = 1 / d``) enters and
    leaves the box ``[lo[j], hi[j]]`` (bounds relative to the sensor): ``(tmin, tmax)``, NaN-aware
    as the vectorised slab test (``np.minimum`` / ``np.maximum`` on the first axis, ``fmax`` /
    ``fmin`` folding the others in)."""
    a, b = lo[j, 0] * ix, hi[j, 0] * ix
    tmin, tmax = _minimum(a, b), _maximum(a, b)
    a, b = lo[j, 1] * iy, hi[j, 1] * iy
    tmin, tmax = _fmax(tmin, _minimum(a, b)), _fmin(tmax, _maximum(a, b))
    a, b = lo[j, 2] * iz, hi[j, 2] * iz
    return _fmax(tmin, _minimum(a, b)), _fmin(tmax, _maximum(a, b))


@njit(inline="always")
def kth_smallest(values, count, rank):
    """The ``rank``-th smallest of ``values[:count]`` (no NaN), partially reordering them in
    place (quickselect, median-of-three pivots): the value ``np.partition`` puts at ``rank``."""
    lo, hi = 0, count - 1
    while hi > lo:
        mid = (lo + hi) >> 1
        a, b, c = values[lo], values[mid], values[hi]
        pivot = max(min(a, b), min(max(a, b), c))
        i, j = lo, hi
        while i <= j:
            while values[i] < pivot:
                i += 1
            while values[j] > pivot:
                j -= 1
            if i <= j:
                values[i], values[j] = values[j], values[i]
                i += 1
                j -= 1
        if rank <= j:
            hi = j
        elif rank >= i:
            lo = i
        else:
            return values[rank]
    return values[rank]


#: :func:`bracketed_kth` samples this many values (at most) to bracket the rank.
BRACKET_SAMPLES = 256
#: ... and keeps the values between the samples this many sample ranks either side of it.
BRACKET_MARGIN = 6


@njit(inline="always")
def bracketed_kth(values, count, rank, spare):
    """:func:`kth_smallest` (the same value, ``values`` left as they are unless it falls back),
    in about one pass for long runs: the rank's value lies, almost surely, between two values of
    an evenly spaced sample a few sample ranks either side of it; one pass counts the values
    below that bracket and copies those inside it to ``spare``, and the selection runs on those
    few. Where the rank is not inside (a sample far from typical), the full selection runs.
    Quickselect on every value took two thirds of the ground's time (Hoare partitions over a
    few thousand heights per box)."""
    if count < 4 * BRACKET_SAMPLES:
        return kth_smallest(values, count, rank)
    step = count // BRACKET_SAMPLES
    n = count // step
    for i in range(n):
        spare[i] = values[i * step]
    at = rank * (n - 1) // (count - 1)
    top = min(at + BRACKET_MARGIN, n - 1)
    hi = kth_smallest(spare, n, top)  # the sample's values before it are now the smaller ones
    lo = kth_smallest(spare, top, max(at - BRACKET_MARGIN, 0)) if top > 0 else hi
    below = inside = 0
    for i in range(count):
        v = values[i]
        if v < lo:
            below += 1
        elif v <= hi:
            spare[inside] = v
            inside += 1
    if below <= rank < below + inside:
        return kth_smallest(spare, inside, rank - below)
    return kth_smallest(values, count, rank)


@compiled()
def ray_keys(az, x, y, z, bins, bands, e0, inv_width, key, slope):
    """Each point's cell of the ray index, ``azimuth bin * (bands + 2) + slope band``, into
    ``key`` (int16) and its slope ``z / r`` into ``slope``, from ``az = arctan2(y, x)`` (numpy's
    SIMD pass; numba's is scalar): the bin ``(az + pi) * bins / 2 pi`` and the band ``(slope - e0)
    * inv_width + 1``, each clipped to its range (NaN to 0, no box's cell), truncated; ``r =
    sqrt(x^2 + y^2)`` at least the smallest normal float. One pass, each step rounded in the
    scan's precision as the numpy passes it replaces did (the same cells and slopes)."""
    dt = slope.dtype.type
    pi, scale, lo, inv = dt(np.pi), dt(bins / (2 * np.pi)), dt(e0), dt(inv_width)
    tiny, one = dt(np.finfo(slope.dtype).tiny), dt(1.0)
    az_top, band_top = dt(bins - 1), dt(bands + 1)
    for i in range(len(x)):
        a = (az[i] + pi) * scale
        a = az_top if a > az_top else (a if a >= 0 else dt(0.0))  # NaN -> 0
        r = np.sqrt(x[i] * x[i] + y[i] * y[i])
        if r < tiny:  # NaN stays NaN
            r = tiny
        sl = z[i] / r
        slope[i] = sl
        band = (sl - lo) * inv + one
        band = band_top if band > band_top else (band if band >= 0 else dt(0.0))
        key[i] = np.int16(np.int16(a) * np.int16(bands + 2) + np.int16(band))


@njit(inline="always")
def _cell_starts(key, wanted, start):
    """``start`` (cells + 1): each cell's first slot of a counting sort of the points whose cell
    ``key`` (``-1``: none) is ``wanted``; returns a copy of the starts to fill from."""
    start[:] = 0
    for i in range(len(key)):
        k = key[i]
        if k >= 0 and wanted[k]:
            start[k + 1] += 1
    for c in range(1, len(start)):
        start[c] += start[c - 1]
    return start[:-1].copy()


@compiled()
def ray_cells(b0, nbins, band_lo, band_hi, bins, stride, first_cell, last_cell, bin_ends, wanted):
    """The cells each judged box ``j`` searches: its ``nbins[j]`` azimuth bins from ``b0[j]``
    (wrapped around ``bins``), each the bands ``band_lo[j] .. band_hi[j]`` of the bin (cell ``bin *
    stride + band``): ``first_cell`` / ``last_cell`` per bin, the running bin count after each box in
    ``bin_ends``; the cells marked in ``wanted`` (all false on entry)."""
    i = 0
    for j in range(len(b0)):
        for k in range(nbins[j]):
            cell = ((b0[j] + k) % bins) * stride
            first_cell[i] = cell + band_lo[j]
            last_cell[i] = cell + band_hi[j]
            for c in range(first_cell[i], last_cell[i] + 1):
                wanted[c] = True
            i += 1
        bin_ends[j] = i


@compiled()
def counting_sort(key, wanted, start, order):
    """The positions of the points whose cell ``key`` (``-1``: none) is ``wanted``, grouped by cell in ``order``
    (ascending positions within a cell); ``start`` (cells + 1) gets each cell's first slot.
    Returns how many points were placed."""
    fill = _cell_starts(key, wanted, start)
    for i in range(len(key)):
        k = key[i]
        if k >= 0 and wanted[k]:
            order[fill[k]] = i
            fill[k] += 1
    return start[len(start) - 1]


@compiled()
def ray_counts(x, y, z, slope, order, start, first_cell, last_cell, bin_ends, boxes_idx, s_lo, s_hi,
               centre, cos, sin, origin, body_lo, body_hi, core_lo, core_hi, out, azimuth, col_lo, col_scale,
               col_count, cols):
    """``out[box, IN / OCCLUDED / STOP / PASS / RAYS]`` += the rays of the cells each judged box
    searches (``first_cell[i] .. last_cell[i]`` for ``i`` in its range of ``bin_ends``; the cells
    sorted by :func:`counting_sort`) whose slope lies in the box's window (the scan's precision)
    and that the float64 slab tests put through the box (definitions in ``docs/filter.md``).

    With ``cols`` (``(boxes, 2)``; an empty array: not measured), the box's azimuth columns too:
    the ray's column is ``(azimuth - col_lo[j]) * col_scale[j]`` (wrapped to a half turn, clipped
    to the ``col_count[j]`` columns); ``cols[box, FILLED]`` counts the columns holding an in-box
    return and ``cols[box, SEEN]`` those holding one or a ray through the core returning from
    beyond it (a column whose every ray ended in front of the box is hidden: not counted)."""
    measure_cols = len(cols) > 0
    width = 0
    if measure_cols:  # one column state array, as wide as the widest box's columns
        for j in range(len(boxes_idx)):
            width = max(width, col_count[j])
    state = np.zeros(width, dtype=np.uint8)
    begin = 0
    for j in range(len(boxes_idx)):
        b = boxes_idx[j]
        cx, cy, cz = centre[b, 0], centre[b, 1], centre[b, 2]
        c, s = cos[b], sin[b]
        ox, oy, oz = origin[b, 0], origin[b, 1], origin[b, 2]
        lo_s, hi_s = s_lo[j], s_hi[j]
        n_in = n_occ = n_stop = n_pass = n_rays = 0
        for i in range(begin, bin_ends[j]):
            for k in range(start[first_cell[i]], start[last_cell[i] + 1]):
                p = order[k]
                sl = slope[p]
                if not (sl >= lo_s and sl <= hi_s):
                    continue
                px = np.float64(x[p]) - cx
                py = np.float64(y[p]) - cy
                dz = np.float64(z[p]) - cz - oz
                dx = c * px + s * py - ox
                dy = c * py - s * px - oy
                ix, iy, iz = 1.0 / dx, 1.0 / dy, 1.0 / dz
                tin, tout = _slab(ix, iy, iz, body_lo, body_hi, b)
                through = tout >= _maximum(tin, 0.0)
                if not through:
                    continue
                cin, cout = _slab(ix, iy, iz, core_lo, core_hi, b)
                core = cout >= _maximum(cin, 0.0)
                before = tin <= 1.0
                inside = 1.0 <= tout and before  # the return lies in the box
                passed = 1.0 > cout and core  # the ray crossed the core and returned from beyond it
                n_rays += 1
                n_in += inside
                n_occ += 1.0 < tin
                n_stop += 1.0 <= cout and core and before
                n_pass += passed
                if measure_cols and (inside or passed):
                    a = np.float64(azimuth[p]) - col_lo[j]
                    a -= 2 * np.pi * np.floor((a + np.pi) / (2 * np.pi))
                    col = min(max(int(np.floor(a * col_scale[j])), 0), col_count[j] - 1)
                    state[col] |= 2 if inside else 1
        begin = bin_ends[j]
        if measure_cols:
            filled = seen = 0
            for col in range(col_count[j]):
                filled += state[col] >= 2
                seen += state[col] > 0
                state[col] = 0
            cols[b, FILLED] = filled
            cols[b, SEEN] = seen
        out[b, IN] = n_in
        out[b, OCCLUDED] = n_occ
        out[b, STOP] = n_stop
        out[b, PASS] = n_pass
        out[b, RAYS] = n_rays


@compiled()
def cell_runs(cx, cy, cos, sin, hl, hw, ox, oy, cell, nx, ny, grow, listed, run_first, run_last, run_ends):
    """Each box's cells of the index grid (``nx`` x ``ny`` cells of ``cell`` metres from ``(ox,
    oy)``; key ``gx * ny + gy``): those whose centre lies within the box grown by ``grow``
    (box frame: ``|cos dx + sin dy| <= hl + grow``, ``|cos dy - sin dx| <= hw + grow``), searched
    over its bounding rectangle widened by a cell, kept off the grid's last row and column.
    Marks them in ``listed``; writes their runs of consecutive keys (one per grid column: the
    centres of a column inside a rectangle are consecutive) to ``run_first`` / ``run_last``
    (room for ``nx`` per box) and the running run count after each box to ``run_ends``. Returns
    the number of runs."""
    count = 0
    for b in range(len(cx)):
        c, s = cos[b], sin[b]
        ex = abs(c) * hl[b] + abs(s) * hw[b]
        ey = abs(s) * hl[b] + abs(c) * hw[b]
        x0 = max(int(np.floor((cx[b] - ex - ox) / cell)) - 1, 0)
        x1 = min(int(np.floor((cx[b] + ex - ox) / cell)) + 1, nx - 1)
        y0 = max(int(np.floor((cy[b] - ey - oy) / cell)) - 1, 0)
        y1 = min(int(np.floor((cy[b] + ey - oy) / cell)) + 1, ny - 1)
        reach_l, reach_w = hl[b] + grow, hw[b] + grow
        for gx in range(x0, x1 + 1):
            dx = ox + (gx + 0.5) * cell - cx[b]
            open_run = False
            for gy in range(y0, y1 + 1):
                dy = oy + (gy + 0.5) * cell - cy[b]
                if abs(c * dx + s * dy) <= reach_l and abs(c * dy - s * dx) <= reach_w:
                    k = gx * ny + gy
                    listed[k] = True
                    if open_run:
                        run_last[count - 1] = k
                    else:
                        run_first[count] = k
                        run_last[count] = k
                        count += 1
                        open_run = True
                elif open_run:
                    break  # the column's cells inside the rectangle are behind
        run_ends[b] = count
    return count


@compiled()
def ground_cells(x, y, z, offset_x, offset_y, scale, nx, ny, zmin, zmax, key):
    """Each point's cell of the ground query's BEV grid (in the scan's precision: ``(x - offset)
    * scale`` clipped into the grid, truncated), or ``-1`` for a point outside ``[zmin, zmax]``
    in height or not finite."""
    for i in range(len(x)):
        zi = z[i]
        if not (zi >= zmin and zi <= zmax):
            key[i] = -1
            continue
        fx = (x[i] - offset_x) * scale
        fy = (y[i] - offset_y) * scale
        # clipped into the grid before the truncation (NaN and off-grid points land in the
        # two-cell border, which no box lists)
        gx = 0 if not fx >= 0 else (nx - 1 if fx > nx - 1 else int(fx))
        gy = 0 if not fy >= 0 else (ny - 1 if fy > ny - 1 else int(fy))
        key[i] = gx * ny + gy


@compiled()
def ground_quantiles(x, y, z, order, start, run_first, run_last, run_ends, zlo, zhi, cx, cy, c, s, hl, hw,
                     quantile, values, spare, out):
    """``out[box]``: the ``int(quantile * (members - 1))``-th smallest height of the box's members
    (the points of its cell runs inside the widened box, tested in the scan's precision as
    :func:`pcc_ros.geometry.boxes.points_in_boxes` does); left as is for a box without members.
    ``values``, ``spare``: work arrays as long as the largest box's candidates."""
    begin = 0
    for b in range(len(run_ends)):
        members = 0
        for r in range(begin, run_ends[b]):
            for k in range(start[run_first[r]], start[run_last[r] + 1]):
                p = order[k]
                pz = z[p]
                if not (pz >= zlo[b] and pz <= zhi[b]):
                    continue
                dx = x[p] - cx[b]
                dy = y[p] - cy[b]
                if abs(c[b] * dx + s[b] * dy) <= hl[b] and abs(c[b] * dy - s[b] * dx) <= hw[b]:
                    values[members] = pz
                    members += 1
        begin = run_ends[b]
        if members:
            out[b] = bracketed_kth(values, members, np.int64(quantile * np.float64(members - 1)), spare)


@compiled()
def expected_counts(boxes_idx, r_lo, n_ring, n_az, ring_cos, ring_sin, cos_az, sin_az, cos, sin,
                    body_lo, body_hi, counts):
    """``counts[j]``: the sensor model's beams (rings ``r_lo[j] ..`` x the first ``n_az[j]``
    sampled columns, directions from ``cos_az`` / ``sin_az`` rows) that the slab test puts through
    judged box ``boxes_idx[j]``."""
    for j in range(len(boxes_idx)):
        b = boxes_idx[j]
        c, s = cos[b], sin[b]
        hits = 0
        for ring in range(r_lo[j], r_lo[j] + n_ring[j]):
            ce, iz = ring_cos[ring], 1.0 / ring_sin[ring]
            for col in range(n_az[j]):
                ex = ce * cos_az[j, col]
                ey = ce * sin_az[j, col]
                tmin, tmax = _slab(1.0 / (c * ex + s * ey), 1.0 / (c * ey - s * ex), iz, body_lo, body_hi, b)
                hits += tmax >= _maximum(tmin, 0.0)
        counts[j] = hits
