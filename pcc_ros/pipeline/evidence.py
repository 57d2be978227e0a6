"""The evidence filter's measurements in the scan: rays towards every box, the sensor model's
expected returns, the local ground (the physics behind :mod:`pcc_ros.pipeline.filter`'s
``density``, ``free_space`` and ``ground_gap`` terms; definitions in ``docs/filter.md``).

Every function here is vectorised over (ray, box), (beam, box) or (point, box) pairs with no
loop over points; the pairs are generated **box by box** (each box's pairs contiguous), so a
per-box value reaches its pairs by ``np.repeat`` over run lengths instead of a gather, and
per-box counts are differences of one cumulative sum. The scan is read in its own precision
(float32 for sensor data) for the index structures; the ray geometry that decides a pair runs
in float64 with the same operations, operand for operand, as the 93cd59e code kept in
``benchmarks/_reference.py`` (``pcc bench filter`` checks the outputs bit-identical).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from pcc_ros.errors import ConfigError, DataError
from pcc_ros.geometry.boxes import box_corners
from pcc_ros.geometry.canonical import to_box_local
from pcc_ros.types import Boxes


@dataclass(frozen=True)
class SensorModel:
    """A spinning LiDAR's beam geometry: ``upper_rings`` beams evenly spread from
    ``elevation_max_deg`` down to ``split_deg[0]``, the other ``rings - upper_rings`` from
    ``split_deg[1]`` down to ``elevation_min_deg`` (one block when ``upper_rings`` is 0), one
    return every ``azimuth_resolution_deg``.

    Presets (datasheets): Velodyne HDL-64E as mounted on KITTI's car (two laser blocks,
    +2.0 .. -8.33 deg and -8.83 .. -24.9 deg, 2083 columns at 10 Hz = 0.1728 deg) and the
    HDL-32E of nuScenes (32 beams +10.67 .. -30.67 deg, 1084 columns at 20 Hz = 0.33 deg).
    """

    rings: int = 64
    elevation_min_deg: float = -24.9
    elevation_max_deg: float = 2.0
    azimuth_resolution_deg: float = 0.1728
    upper_rings: int = 32
    split_deg: tuple[float, float] = (-8.33, -8.83)

    def __post_init__(self) -> None:
        if (
            self.rings < 2
            or self.azimuth_resolution_deg <= 0
            or self.elevation_max_deg <= self.elevation_min_deg
            or not 0 <= self.upper_rings < self.rings
        ):
            raise ConfigError(f"bad sensor model {self}")

    def ring_elevations(self) -> np.ndarray:
        """Ascending beam elevations, radians."""
        if self.upper_rings == 0:
            degrees = np.linspace(self.elevation_min_deg, self.elevation_max_deg, self.rings)
        else:
            upper = np.linspace(self.split_deg[0], self.elevation_max_deg, self.upper_rings)
            lower = np.linspace(self.elevation_min_deg, self.split_deg[1], self.rings - self.upper_rings)
            degrees = np.r_[lower, upper]
        return np.deg2rad(np.sort(degrees))


SENSOR_PRESETS = {
    "hdl64": SensorModel(64, -24.9, 2.0, 0.1728, 32, (-8.33, -8.83)),
    "hdl32": SensorModel(32, -30.67, 10.67, 0.33, 0, (0.0, 0.0)),
}

#: The solid core of a car body inside its box, as fractions of the box (length, width) and of
#: its height from the bottom: below the windows, above the gap under the chassis. Rays that
#: cross this core and return from beyond it say the box is empty.
CORE_FRACTION = (0.8, 0.8)
CORE_Z = (0.2, 0.6)
#: Returns lower than this above the box bottom are ground (counted as passing, not as car).
EVIDENCE_GROUND = 0.3
#: The local ground is the 5 % quantile of the heights of the returns within this many metres
#: of the box footprint (all around it: the returns beside a car reach the ground it hides).
GROUND_REACH = 3.0
#: BEV cell (metres) of the ground query's index (coarsened when the boxes spread so far that
#: the grid would exceed :data:`_MAX_CELLS`).
_GROUND_CELL = 1.0
#: Cells of an index grid: below 2^15, so a cell key is an int16 (numpy's radix sort).
_MAX_CELLS = 32_000
#: Most beam columns sampled per box for the expected return count.
EXPECTED_COLUMNS = 64
#: Bins of the ray index: 0.2 deg of azimuth times 16 bands of elevation spanning the boxes'
#: elevation windows, plus one band below and one above them (rays no box can meet); the
#: product stays below 2^15 so the bin key is an int16.
_AZ_BINS = 1800
_EL_BANDS = 16
#: Slack of the ray index's elevation test (on the slope z / r of the ray, in the scan's
#: precision): it must stay a superset of the rays that reach a box (the exact float64 box
#: test comes after); orders of magnitude above float32 rounding of a slope.
_SLOPE_SLACK = 1e-4
#: Slack (metres) of the ground query's cell test: a point the exact test (in the scan's
#: precision) accepts lies in a cell listed for the box even after float32 rounding.
_GROUND_SLACK = 0.01


@dataclass
class Evidence:
    """Per-detection raw measurements and the derived terms (one row per box)."""

    n_in: np.ndarray  # returns inside the box above the ground band
    n_stop: np.ndarray  # rays through the core that ended inside the box
    n_pass: np.ndarray  # rays through the core that returned from beyond it
    n_occluded: np.ndarray  # rays towards the box that ended in front of it
    n_rays: np.ndarray  # scan rays towards the box (all outcomes)
    expected: np.ndarray  # beams of the sensor model that hit the box
    ground_z: np.ndarray  # local ground height under the box (NaN: none seen)
    terms: dict[str, np.ndarray]

    def as_dict(self) -> dict[str, np.ndarray]:
        names = ("n_in", "n_stop", "n_pass", "n_occluded", "n_rays", "expected", "ground_z")
        raw = {k: getattr(self, k) for k in names}
        return {**raw, **self.terms}


class _BoxTable:
    """Per-box values of the ray geometry, computed once per frame (every value is the one a
    per-pair computation would give: same operands, same order)."""

    def __init__(self, boxes: Boxes) -> None:
        self.cos, self.sin = np.cos(boxes.yaw), np.sin(boxes.yaw)
        cx, cy, cz = boxes.center.T
        # the sensor (the scan frame's origin) in each box's frame
        self.origin = np.stack(to_box_local(0.0, 0.0, 0.0, cx, cy, cz, self.cos, self.sin), axis=1)
        half = boxes.size / 2
        body_lo, body_hi = -half.copy(), half.copy()
        body_lo[:, 2] += EVIDENCE_GROUND
        scale = np.array([CORE_FRACTION[0], CORE_FRACTION[1], 1.0])
        core_lo, core_hi = -half * scale, half * scale
        core_lo[:, 2] = -half[:, 2] + CORE_Z[0] * 2 * half[:, 2]
        core_hi[:, 2] = -half[:, 2] + CORE_Z[1] * 2 * half[:, 2]
        # slab bounds relative to the ray origin: (lo - origin), (hi - origin), per axis
        self.body = (body_lo - self.origin, body_hi - self.origin)
        self.core = (core_lo - self.origin, core_hi - self.origin)


def angular_window(boxes: Boxes) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
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


def _runs(lo: np.ndarray, length: np.ndarray) -> np.ndarray:
    """The concatenated ranges ``lo[i] .. lo[i] + length[i] - 1`` (int64), without a loop."""
    ends = np.cumsum(length)
    total = int(ends[-1]) if len(ends) else 0
    return np.arange(total, dtype=np.int64) + np.repeat(lo - (ends - length), length)


def _segment_counts(mask: np.ndarray, ends: np.ndarray) -> np.ndarray:
    """True values of ``mask`` per contiguous segment ending (exclusive) at ``ends`` (int64):
    where the segment ends fall among the true positions."""
    return np.diff(np.searchsorted(np.flatnonzero(mask), ends), prepend=0)


def _slab_axis(inv, lo, hi, tmin, tmax):
    """One axis of the slab test (``lo``, ``hi``: the bounds relative to the ray origin, per
    pair); the running entry / exit parameters, as the 93cd59e code: fmax / fmin skip the NaN of
    a ray parallel to a slab starting on its plane."""
    t1 = lo * inv
    t2 = hi * inv
    near, far = np.minimum(t1, t2), np.maximum(t1, t2)
    if tmin is None:
        return near, far
    return np.fmax(tmin, near, out=tmin), np.fmin(tmax, far, out=tmax)


def _ray_pairs(x, y, z, az_lo, az_hi, el_lo, el_hi, judged):
    """The ray index: the points whose ray from the sensor lies in some judged box's angular
    window (a superset of the rays that cross the box; :func:`evidence` tests them exactly).

    One pass over the scan in its own precision gives every point's azimuth bin; only the
    points in a bin some box needs (its azimuth sector, widened by one bin each way) go on:
    their slope ``z / r`` (monotone in elevation), a radix sort into (azimuth, slope band)
    bins; each box's azimuth bins expand into the contiguous run of its bands without a
    Python loop, and the box's slope window (with a slack far above float32 rounding) is
    tested per pair. Non-finite points never pair.

    Returns ``(sub, pair_point, box_ends)``: ``sub`` the scan positions of the points that
    entered the index, ``pair_point`` positions in ``sub``, box by box (the judged boxes in
    order), and ``box_ends`` the end (exclusive) of each judged box's pairs.
    """
    boxes_idx = np.flatnonzero(judged)
    m = len(boxes_idx)
    empty = np.zeros(0, np.int64)
    if not m or not len(x):
        return empty, empty, np.zeros(m, np.int64)
    dt = x.dtype.type
    # Windows in slope space, widened by the slack; bands span the boxes' windows.
    s_lo = np.tan(el_lo[boxes_idx]) - _SLOPE_SLACK * (1.0 + np.tan(el_lo[boxes_idx]) ** 2)
    s_hi = np.tan(el_hi[boxes_idx]) + _SLOPE_SLACK * (1.0 + np.tan(el_hi[boxes_idx]) ** 2)
    e0 = float(s_lo.min())
    width = max(float(s_hi.max()) - e0, 1e-6) / _EL_BANDS
    b0 = np.floor((az_lo[boxes_idx] + np.pi) * (_AZ_BINS / (2 * np.pi))).astype(np.int64) - 1
    b1 = np.floor((az_hi[boxes_idx] + np.pi) * (_AZ_BINS / (2 * np.pi))).astype(np.int64) + 1
    nbins = np.minimum(b1 - b0 + 1, _AZ_BINS)
    box_of_bin = np.repeat(np.arange(m), nbins)
    az_bin = (np.repeat(b0, nbins) + _runs(np.zeros(m, np.int64), nbins)) % _AZ_BINS
    with np.errstate(invalid="ignore"):
        scaled = np.arctan2(y, x)
        scaled += dt(np.pi)
        scaled *= dt(_AZ_BINS / (2 * np.pi))
        np.fmax(scaled, 0, out=scaled)  # NaN -> 0 (band 0 below: no box)
        np.fmin(scaled, _AZ_BINS - 1, out=scaled)
    key = scaled.astype(np.int16)
    wanted = np.zeros(_AZ_BINS, dtype=bool)
    wanted[az_bin] = True
    sub = np.flatnonzero(np.take(wanted, key))
    key = np.take(key, sub)
    xs, ys, zs = (np.take(a, sub) for a in (x, y, z))
    with np.errstate(invalid="ignore", divide="ignore"):
        r = xs * xs
        r += ys * ys
        np.sqrt(r, out=r)
        # A return at the sensor (0, 0, 0) has slope 0, as arctan2(0, 0) = 0 (the 93cd59e
        # index paired it with the boxes at azimuth and elevation 0); straight up / down is
        # beyond every box's window; NaN points stay NaN.
        np.fmax(r, np.finfo(dt).tiny, out=r)
        slope = np.divide(zs, r, out=r)
        band = (slope - dt(e0)) * dt(1.0 / width)
        band += 1
        np.fmax(band, 0, out=band)  # NaN -> band 0: no box
        np.fmin(band, _EL_BANDS + 1, out=band)
    key *= np.int16(_EL_BANDS + 2)
    key += band.astype(np.int16)
    n_bins = _AZ_BINS * (_EL_BANDS + 2)
    order = np.argsort(key, kind="stable")
    starts = np.zeros(n_bins + 1, dtype=np.int64)
    np.cumsum(np.bincount(key, minlength=n_bins), out=starts[1:])
    band_lo = np.clip(np.floor((s_lo - e0) / width).astype(np.int64), 1, _EL_BANDS)  # one band wider below
    band_hi = np.clip(np.floor((s_hi - e0) / width).astype(np.int64) + 2, 1, _EL_BANDS)  # and above
    bins = az_bin * (_EL_BANDS + 2)
    lo = starts[bins + np.take(band_lo, box_of_bin)]
    count = starts[bins + np.take(band_hi, box_of_bin) + 1] - lo
    pair_point = np.take(order, _runs(lo, count))
    per_box = np.bincount(box_of_bin, weights=count, minlength=m).astype(np.int64)
    s = np.take(slope, pair_point)
    with np.errstate(invalid="ignore"):
        keep = s >= np.repeat(s_lo.astype(dt), per_box)
        keep &= s <= np.repeat(s_hi.astype(dt), per_box)
    kept = np.flatnonzero(keep)
    return sub, np.take(pair_point, kept), np.searchsorted(kept, np.cumsum(per_box))


def _ray_counts(x, y, z, boxes: Boxes, table: _BoxTable, window) -> tuple[np.ndarray, ...]:
    """``n_in, n_occluded, n_stop, n_pass, n_rays`` of every box (float64)."""
    n = len(boxes)
    judged = window[4]
    boxes_idx = np.flatnonzero(judged)
    sub, pair_point, box_ends = _ray_pairs(x, y, z, *window)
    zero = np.zeros(n)
    if not len(pair_point):
        return zero, zero.copy(), zero.copy(), zero.copy(), zero.copy()
    per_box = np.diff(box_ends, prepend=0)

    def rep(values: np.ndarray) -> np.ndarray:  # a per-box value on each of its pairs
        return np.repeat(values[boxes_idx], per_box)

    # Box-frame ray: origin (the sensor, one per box) + t * (point - origin); t = 1 at the return.
    point = np.take(sub, pair_point)
    px, py, pz = (np.take(a, point).astype(np.float64) for a in (x, y, z))
    c, s = rep(table.cos), rep(table.sin)
    px -= rep(boxes.center[:, 0])  # dx
    py -= rep(boxes.center[:, 1])  # dy
    pz -= rep(boxes.center[:, 2])  # the local z
    lx = c * px
    lx += s * py
    ly = c * py
    ly -= s * px
    lx -= rep(table.origin[:, 0])
    ly -= rep(table.origin[:, 1])
    pz -= rep(table.origin[:, 2])
    tin = tout = cin = cout = None
    with np.errstate(divide="ignore", invalid="ignore"):
        for axis, d in enumerate((lx, ly, pz)):
            inv = np.divide(1.0, d, out=d)
            tin, tout = _slab_axis(inv, rep(table.body[0][:, axis]), rep(table.body[1][:, axis]), tin, tout)
            cin, cout = _slab_axis(inv, rep(table.core[0][:, axis]), rep(table.core[1][:, axis]), cin, cout)
    through = tout >= np.maximum(tin, 0.0)  # rays that cross the box at all
    through_core = cout >= np.maximum(cin, 0.0)
    through_core &= through
    before = tin <= 1.0
    inside = before & (1.0 <= tout)
    inside &= through
    occluded = (1.0 < tin) & through
    stop = through_core & before
    stop &= 1.0 <= cout
    passed = through_core & (1.0 > cout)
    out = []
    for mask in (inside, occluded, stop, passed, through):
        full = np.zeros(n)
        full[boxes_idx] = _segment_counts(mask, box_ends)
        out.append(full)
    return tuple(out)


def _expected_beams(boxes: Boxes, sensor: SensorModel, az_lo, az_hi, el_lo, el_hi, judged,
                    table: _BoxTable | None = None) -> np.ndarray:
    """Beams of the sensor model (rings x azimuth steps) whose rays hit each box.

    The beams of a box are a (ring, column) grid: one row per (box, ring), the columns padded
    to :data:`EXPECTED_COLUMNS`, so the trigonometry and the box rotation broadcast over rows and
    columns (no per-beam gathers); padding columns do not count."""
    out = np.zeros(len(boxes))
    rings = sensor.ring_elevations()
    step = np.deg2rad(sensor.azimuth_resolution_deg)
    idx = np.flatnonzero(judged)
    if not len(idx):
        return out
    table = table or _BoxTable(boxes)
    n_az_full = np.floor((az_hi[idx] - az_lo[idx]) / step).astype(np.int64) + 1
    # A near box spans hundreds of columns: sample at most EXPECTED_COLUMNS of them, evenly,
    # and scale the count back (an unbiased estimate; exact for far boxes).
    n_az = np.minimum(n_az_full, EXPECTED_COLUMNS)
    stretch = n_az_full / n_az
    r_lo = np.searchsorted(rings, el_lo[idx])
    r_hi = np.searchsorted(rings, el_hi[idx], side="right")
    n_ring = np.maximum(r_hi - r_lo, 0)
    if not n_ring.sum():
        return out
    width = int(n_az.max())
    column = np.arange(width)
    azimuth = az_lo[idx][:, None] + (column + 0.5) * step * stretch[:, None]  # (boxes, columns)
    cos_az, sin_az = np.cos(azimuth), np.sin(azimuth)
    row_box = np.repeat(np.arange(len(idx)), n_ring)  # one row per (box, ring)
    ring = np.repeat(r_lo, n_ring) + _runs(np.zeros(len(idx), np.int64), n_ring)
    ce = np.cos(rings)[ring][:, None]
    box = idx[row_box]
    c, s = table.cos[box][:, None], table.sin[box][:, None]
    dx = ce * cos_az[row_box]
    dy = ce * sin_az[row_box]
    direction = (c * dx + s * dy, c * dy - s * dx, np.sin(rings)[ring][:, None])
    tmin = tmax = None
    with np.errstate(divide="ignore", invalid="ignore"):
        for axis in range(3):
            inv = 1.0 / direction[axis]
            tmin, tmax = _slab_axis(inv, table.body[0][box, axis][:, None], table.body[1][box, axis][:, None],
                                    tmin, tmax)
    hit = tmax >= np.maximum(tmin, 0.0)
    hit &= column < n_az[row_box][:, None]
    per_box = np.bincount(row_box, weights=hit.sum(axis=1), minlength=len(idx))
    out[idx] = per_box * stretch
    return out


def _outward(values: np.ndarray, dt: type, up: bool) -> np.ndarray:
    """``values`` rounded to ``dt`` outward: the smallest ``dt`` numbers >= them (``up``) or the
    largest <= them, so a test of ``dt`` points against them equals the exact float64 test."""
    out = values.astype(dt)
    if up:
        return np.where(out < values, np.nextafter(out, dt(np.inf)), out)
    return np.where(out > values, np.nextafter(out, dt(-np.inf)), out)


def _ground(x, y, z, boxes: Boxes, reach: float, quantile: float) -> np.ndarray:
    """:func:`local_ground` on the scan's coordinate columns (contiguous, one dtype)."""
    n = len(boxes)
    out = np.full(n, np.nan)
    bottom = boxes.center[:, 2] - boxes.size[:, 2] / 2
    wide = Boxes(np.c_[boxes.center[:, :2], bottom - 1.0], np.c_[boxes.size[:, :2] + 2 * reach, np.full(n, 4.0)],
                 boxes.yaw)
    if not wide.valid_mask().all():
        wide.validate()
    if not len(x):
        return out
    dt = x.dtype.type
    half = wide.size / 2.0
    # The test of a point against a box runs in the scan's precision, on box-relative x / y,
    # the z bounds rounded outward (as geometry.boxes.points_in_boxes, which this reproduces).
    zlo = _outward(wide.center[:, 2] - half[:, 2], dt, up=True)
    zhi = _outward(wide.center[:, 2] + half[:, 2], dt, up=False)
    cx, cy = wide.center[:, 0].astype(dt), wide.center[:, 1].astype(dt)
    cos64, sin64 = np.cos(wide.yaw), np.sin(wide.yaw)
    c, s = cos64.astype(dt), sin64.astype(dt)
    hl, hw = half[:, 0].astype(dt), half[:, 1].astype(dt)
    # BEV index: a grid over the boxes; each box lists the cells that can hold a point it
    # contains (cell centre within the box grown by half a cell diagonal and a slack).
    corners = box_corners(wide)[:, :4, :2]
    lo, hi = corners.min(axis=1), corners.max(axis=1)
    cell = _GROUND_CELL
    span = hi.max(axis=0) - lo.min(axis=0)
    while np.prod(np.floor(span / cell) + 5) > _MAX_CELLS:  # boxes spread far apart: coarser cells
        cell *= 1.5
    # two cells of margin on every side: a point off the grid is off every box
    origin = lo.min(axis=0) - 2 * cell
    nx, ny = (int(v) for v in np.floor(span / cell) + 5)
    c0 = np.floor((lo - origin) / cell).astype(np.int64) - 1
    c1 = np.floor((hi - origin) / cell).astype(np.int64) + 1
    c0, c1 = np.maximum(c0, 0), np.minimum(c1, [nx - 1, ny - 1])
    extent = c1 - c0 + 1
    per_box = extent[:, 0] * extent[:, 1]
    box_of = np.repeat(np.arange(n), per_box)
    local = _runs(np.zeros(n, np.int64), per_box)
    gx = c0[box_of, 0] + local // extent[box_of, 1]
    gy = c0[box_of, 1] + local % extent[box_of, 1]
    ccx, ccy, _ = to_box_local(origin[0] + (gx + 0.5) * cell, origin[1] + (gy + 0.5) * cell, 0.0,
                               wide.center[box_of, 0], wide.center[box_of, 1], 0.0, cos64[box_of], sin64[box_of])
    grow = cell * np.sqrt(0.5) + _GROUND_SLACK
    touch = (np.abs(ccx) <= half[box_of, 0] + grow) & (np.abs(ccy) <= half[box_of, 1] + grow)
    box_of, key = box_of[touch], gx[touch] * ny + gy[touch]  # box-major, cells ascending
    # The points: z within the boxes' union range and on the grid, sorted by cell (radix).
    with np.errstate(invalid="ignore"):
        fx = x - dt(origin[0])
        fx *= dt(1.0 / cell)
        fy = y - dt(origin[1])
        fy *= dt(1.0 / cell)
        ok = z >= zlo.min()
        ok &= z <= zhi.max()
        ok &= fx >= 0
        ok &= fx < nx
        ok &= fy >= 0
        ok &= fy < ny
    pts = np.flatnonzero(ok)
    if not len(pts):
        return out
    pkey = np.take(fx, pts).astype(np.int16)
    pkey *= np.int16(ny)
    pkey += np.take(fy, pts).astype(np.int16)
    order = np.argsort(pkey, kind="stable")
    starts = np.zeros(nx * ny + 1, dtype=np.int64)
    np.cumsum(np.bincount(pkey, minlength=nx * ny), out=starts[1:])
    pts = np.take(pts, order)
    xs, ys, zs = (np.take(a, pts) for a in (x, y, z))
    # A box's consecutive cells are one run of the sorted points.
    if len(key):
        new = np.ones(len(key), dtype=bool)
        new[1:] = (np.diff(key) != 1) | (np.diff(box_of) != 0)
        first = np.flatnonzero(new)
        last = np.r_[first[1:], len(key)] - 1
        run_lo, run_hi, run_box = starts[key[first]], starts[key[last] + 1], box_of[first]
    else:
        run_lo = run_hi = run_box = np.zeros(0, np.int64)
    length = run_hi - run_lo
    pair = _runs(run_lo, length)
    box_pairs = np.bincount(run_box, weights=length, minlength=n).astype(np.int64)
    px, py, pz = (np.take(a, pair) for a in (xs, ys, zs))

    def rep(values: np.ndarray) -> np.ndarray:
        return np.repeat(values, box_pairs)

    keep = pz >= rep(zlo)
    keep &= pz <= rep(zhi)
    px -= rep(cx)  # dx
    py -= rep(cy)  # dy
    cb, sb = rep(c), rep(s)
    lx = cb * px
    lx += sb * py
    ly = cb * py
    ly -= sb * px
    keep &= np.abs(lx, out=lx) <= rep(hl)
    keep &= np.abs(ly, out=ly) <= rep(hw)
    kept = np.flatnonzero(keep)
    ends = np.searchsorted(kept, np.cumsum(box_pairs)).tolist()
    members = np.take(pz, kept)
    for b, (start, end) in enumerate(zip([0, *ends[:-1]], ends)):  # one partial sort per box (boxes, not points)
        if end > start:
            k = int(quantile * (end - start - 1))
            out[b] = np.partition(members[start:end], k)[k]
    return out


def _columns(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Contiguous x, y, z columns in the scan's precision (float32 stays float32, others
    become float64): numpy's SIMD loops skip strided arrays."""
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] < 3:
        raise DataError(f"points must be (N, >=3), got shape {points.shape}")
    dt = np.float32 if points.dtype == np.float32 else np.float64
    return tuple(np.ascontiguousarray(points[:, k], dtype=dt) for k in range(3))


def local_ground(points: np.ndarray, boxes: Boxes, reach: float = GROUND_REACH, quantile: float = 0.05) -> np.ndarray:
    """Ground height around each box: the ``quantile`` of the z of the returns within ``reach``
    metres of its footprint and from 3 m below to 1 m above its bottom (NaN when there are none).

    The returns are those :func:`pcc_ros.geometry.boxes.points_in_boxes` finds in the widened
    boxes (same test, in the scan's precision), found through a BEV grid whose cells are sorted
    once: each box's cells are runs of the sorted points, generated box by box."""
    if len(boxes) == 0:
        return np.zeros(0)
    return _ground(*_columns(points), boxes, reach, quantile)


_SIDE_POOL: ThreadPoolExecutor | None = None


def _side_pool() -> ThreadPoolExecutor:
    global _SIDE_POOL
    if _SIDE_POOL is None:
        _SIDE_POOL = ThreadPoolExecutor(max_workers=1, thread_name_prefix="pcc-filter")
    return _SIDE_POOL


def evidence(points: np.ndarray, boxes: Boxes, sensor: SensorModel | None = None, workers: int = 1) -> Evidence:
    """Free-space, return-count and ground-contact measurements of every box, from the scan.

    The sensor sits at the scan frame's origin (true for a scan in its own sensor frame).
    Vectorised over (ray, box) pairs generated box by box: no loop over points or boxes; the
    pairs' geometry runs column by column in float64 on per-box values repeated over each
    box's run. ``workers`` >= 2: the sensor model's expected returns and the local ground (a
    query of its own over the scan) are measured on a second thread while this one follows
    the rays (numpy releases the GIL in its loops); the values are the same either way.
    """
    sensor = sensor or SensorModel()
    n = len(boxes)
    zero = np.zeros(n)
    if n == 0:
        return Evidence(*([zero] * 7), _derive(*([zero] * 7), boxes))
    if not boxes.valid_mask().all():
        boxes.validate()  # DataError naming the box
    x, y, z = _columns(points)
    window = angular_window(boxes)
    table = _BoxTable(boxes)

    def beams_and_ground() -> tuple[np.ndarray, np.ndarray]:
        return (_expected_beams(boxes, sensor, *window, table=table),
                _ground(x, y, z, boxes, GROUND_REACH, 0.05))

    side_job = _side_pool().submit(beams_and_ground) if workers > 1 else None
    n_in, n_occ, n_stop, n_pass, n_rays = _ray_counts(x, y, z, boxes, table, window)
    expected, ground = side_job.result() if side_job is not None else beams_and_ground()
    return Evidence(
        n_in, n_stop, n_pass, n_occ, n_rays, expected, ground,
        _derive(n_in, n_stop, n_pass, n_occ, n_rays, expected, ground, boxes),
    )


def _derive(n_in, n_stop, n_pass, n_occ, n_rays, expected, ground, boxes: Boxes) -> dict[str, np.ndarray]:
    """The dimensionless terms the score combines (documented in docs/filter.md)."""
    visible = np.where(n_rays > 0, 1.0 - n_occ / np.maximum(n_rays, 1.0), 1.0)
    density = np.log((n_in + 1.0) / (expected * visible + 1.0))
    free_space = np.log((n_pass + 0.5) / (n_stop + 0.5))
    bottom = boxes.center[:, 2] - boxes.size[:, 2] / 2
    gap = np.abs(bottom - ground)
    ground_gap = np.where(np.isfinite(gap), np.minimum(gap, 3.0), 0.0)
    return {"density": density, "free_space": free_space, "ground_gap": ground_gap}
