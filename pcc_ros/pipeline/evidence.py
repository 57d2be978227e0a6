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

import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from pcc_ros.errors import ConfigError, DataError
from pcc_ros.geometry.boxes import box_corners, round_down_to, round_up_to
from pcc_ros.geometry.canonical import to_box_local
from pcc_ros.geometry.segments import positions_in_runs
from pcc_ros.scratch import Scratch
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


@lru_cache(maxsize=16)
def _ring_table(sensor: SensorModel) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``sensor.ring_elevations()`` with their cosines and sines, computed once per sensor
    model (about 90 us a call: a constant of the frame loop); read-only."""
    rings = sensor.ring_elevations()
    table = (rings, np.cos(rings), np.sin(rings))
    for values in table:
        values.flags.writeable = False
    return table


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
#: The ray index works on the points of the boxes' azimuth sectors only when these cover less
#: than this share of the circle.
_SUBSET_SHARE = 0.75
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


_SCRATCH = Scratch()  # this module's work arrays (pcc_ros.scratch)


def _segment_counts(mask: np.ndarray, ends: np.ndarray) -> np.ndarray:
    """True values of ``mask`` per contiguous segment ending (exclusive) at ``ends`` (int64)."""
    out = np.zeros(len(ends), dtype=np.int64)
    starts = np.zeros(len(ends), dtype=np.int64)
    starts[1:] = ends[:-1]
    nonempty = np.flatnonzero(ends > starts)
    if len(nonempty):
        out[nonempty] = np.add.reduceat(mask, starts[nonempty], dtype=np.int64)
    return out


def _clamp(values: np.ndarray, hi: int, nan: np.ndarray) -> None:
    """``values`` clipped to ``[0, hi]`` in place, NaN to 0 (``nan``: a work mask). What
    ``fmin(fmax(values, 0), hi)`` gives, at a third of its cost (numpy's fmax / fmin with a
    scalar take no SIMD path)."""
    np.clip(values, 0, hi, out=values)
    np.copyto(values, 0, where=np.isnan(values, out=nan))


def _ray_pairs(x, y, z, az_lo, az_hi, el_lo, el_hi, judged, ws: Scratch):
    """The ray index: the points whose ray from the sensor lies in some judged box's angular
    window (a superset of the rays that cross the box; :func:`evidence` tests them exactly).

    Passes over the scan in its own precision give every point's azimuth bin and slope
    ``z / r`` (monotone in elevation; contiguous passes cost less than gathering a subset's
    coordinates); only the (azimuth, slope band) keys of the points in a bin some box needs
    (its azimuth sector, widened by one bin each way) go into a radix sort; each box's
    azimuth bins expand into the contiguous run of its bands without a
    Python loop, and the box's slope window (with a slack far above float32 rounding) is
    tested per pair. Non-finite points never pair.

    Returns ``(point, box_ends)``: the scan positions of the pairs' points, box by box (the
    judged boxes in order), and the end (exclusive) of each judged box's pairs.
    """
    boxes_idx = np.flatnonzero(judged)
    m = len(boxes_idx)
    if not m or not len(x):
        return np.zeros(0, np.int64), np.zeros(m, np.int64)
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
    az_bin = (np.repeat(b0, nbins) + positions_in_runs(nbins)) % _AZ_BINS
    n = len(x)
    with np.errstate(invalid="ignore"):
        scaled = np.arctan2(y, x, out=ws("az", n, dt))
        scaled += dt(np.pi)
        scaled *= dt(_AZ_BINS / (2 * np.pi))
        _clamp(scaled, _AZ_BINS - 1, ws("nan", n, bool))  # NaN -> 0 (band 0 below: no box)
    key = ws("key", n, np.int16)
    np.copyto(key, scaled, casting="unsafe")  # truncation: the floor of these non-negative bins
    with np.errstate(invalid="ignore", divide="ignore"):
        r = np.multiply(x, x, out=ws("r", n, dt))
        tmp = ws("tmp", n, dt)
        r += np.multiply(y, y, out=tmp)
        np.sqrt(r, out=r)
        # A return at the sensor (0, 0, 0) has slope 0, as arctan2(0, 0) = 0 (the 93cd59e
        # index paired it with the boxes at azimuth and elevation 0); straight up / down is
        # beyond every box's window; NaN points stay NaN.
        np.clip(r, np.finfo(dt).tiny, np.inf, out=r)
        slope = np.divide(z, r, out=r)
        band = np.subtract(slope, dt(e0), out=tmp)
        band *= dt(1.0 / width)
        band += 1
        _clamp(band, _EL_BANDS + 1, ws("nan", n, bool))  # NaN -> band 0: no box
    band16 = ws("band", n, np.int16)
    np.copyto(band16, band, casting="unsafe")
    key *= np.int16(_EL_BANDS + 2)
    key += band16
    band_lo = np.clip(np.floor((s_lo - e0) / width).astype(np.int64), 1, _EL_BANDS)  # one band wider below
    band_hi = np.clip(np.floor((s_hi - e0) / width).astype(np.int64) + 2, 1, _EL_BANDS)  # and above
    bins = az_bin * (_EL_BANDS + 2)
    # The (azimuth bin, band) cells some box searches: the points outside them cannot pair (a
    # table lookup), unless the boxes' azimuth sectors cover most of the circle (then selecting
    # costs more than it saves).
    first_cell = bins + np.take(band_lo, box_of_bin)
    sub = None
    sectors = np.zeros(_AZ_BINS, dtype=bool)
    sectors[az_bin] = True
    if np.count_nonzero(sectors) < _SUBSET_SHARE * _AZ_BINS:
        n_cells = np.take(band_hi - band_lo + 1, box_of_bin)
        wanted = np.zeros(_AZ_BINS * (_EL_BANDS + 2), dtype=bool)
        wanted[np.repeat(first_cell, n_cells) + positions_in_runs(n_cells)] = True
        sub = ws.nonzero(wanted.take(key, out=ws("want", n, bool), mode="clip"), "sub")
        key = key.take(sub, out=ws("key_s", len(sub), np.int16), mode="clip")
    order = np.argsort(key, kind="stable")
    # Each (box, azimuth bin)'s bands are one range of the sorted keys: its bounds by binary
    # search (int16 queries: the keys are not converted), not a count of every bin.
    ordered = key.take(order, out=ws("key_sorted", len(key), np.int16), mode="clip")
    lo = np.searchsorted(ordered, first_cell.astype(np.int16), side="left")
    count = np.searchsorted(ordered, (bins + np.take(band_hi, box_of_bin)).astype(np.int16), side="right") - lo
    candidates = ws.runs(lo, count, "runs")
    q = len(candidates)
    pair = order.take(candidates, out=ws("pair", q, np.int64), mode="clip")
    del order
    if sub is not None:  # positions in the scan
        pair = sub.take(pair, out=ws("pair_scan", q, np.int64), mode="clip")
    s = slope.take(pair, out=ws("s", q, dt), mode="clip")
    per_box = np.bincount(box_of_bin, weights=count, minlength=m).astype(np.int64)
    with np.errstate(invalid="ignore"):
        keep = np.greater_equal(s, np.repeat(s_lo.astype(dt), per_box), out=ws("keep", q, bool))
        keep &= np.less_equal(s, np.repeat(s_hi.astype(dt), per_box), out=ws("keep2", q, bool))
    kept = ws.nonzero(keep, "kept")
    point = pair.take(kept, out=candidates[: len(kept)], mode="clip")
    return point, np.searchsorted(kept, np.cumsum(per_box))


def _ray_counts(x, y, z, boxes: Boxes, table: _BoxTable, window, ws: Scratch) -> tuple[np.ndarray, ...]:
    """``n_in, n_occluded, n_stop, n_pass, n_rays`` of every box (float64)."""
    n = len(boxes)
    boxes_idx = np.flatnonzero(window[4])
    point, box_ends = _ray_pairs(x, y, z, *window, ws)
    if not len(point):
        return tuple(np.zeros(n) for _ in range(5))
    p = len(point)
    f64 = np.float64

    per_box = np.diff(box_ends, prepend=0)

    def rep(values: np.ndarray) -> np.ndarray:  # a per-box value on each of its pairs
        return np.repeat(values[boxes_idx], per_box)  # a transient array (cheaper than a gather)

    a, b, d = (ws(name, p, f64) for name in ("r_a", "r_b", "r_d"))
    px, py, pz = (ws(name, p, f64) for name in ("r_px", "r_py", "r_pz"))
    # Box-frame ray: origin (the sensor, one per box) + t * (point - origin); t = 1 at the return;
    # the operations of to_box_local (on the point in float64), then minus the origin.
    for column, centre, out in ((x, 0, px), (y, 1, py), (z, 2, pz)):
        if column.dtype == f64:
            column.take(point, out=out, mode="clip")
        else:  # a gather in the scan's precision, then one widening copy (faster than a mixed subtraction)
            np.copyto(out, column.take(point, out=ws("r_gather", p, column.dtype), mode="clip"))
        out -= rep(boxes.center[:, centre])  # dx, dy, local z
    c, s = rep(table.cos), rep(table.sin)
    lx = np.multiply(c, px, out=ws("r_lx", p, f64))
    lx += np.multiply(s, py, out=a)
    ly = np.multiply(c, py, out=ws("r_ly", p, f64))
    ly -= np.multiply(s, px, out=a)
    lx -= rep(table.origin[:, 0])
    ly -= rep(table.origin[:, 1])
    pz -= rep(table.origin[:, 2])
    tin, tout, cin, cout = px, py, ws("r_cin", p, f64), ws("r_cout", p, f64)  # px, py free again
    with np.errstate(divide="ignore", invalid="ignore"):
        for axis, direction in enumerate((lx, ly, pz)):
            inv = np.divide(1.0, direction, out=direction)
            for (lo, hi), tmin, tmax in ((table.body, tin, tout), (table.core, cin, cout)):
                np.multiply(rep(lo[:, axis]), inv, out=a)  # lo * inv
                np.multiply(rep(hi[:, axis]), inv, out=b)
                # fmax / fmin skip the NaN of a ray parallel to a slab starting on its plane
                if axis == 0:
                    np.minimum(a, b, out=tmin)
                    np.maximum(a, b, out=tmax)
                else:
                    np.fmax(tmin, np.minimum(a, b, out=d), out=tmin)
                    np.fmin(tmax, np.maximum(a, b, out=a), out=tmax)
        through = np.greater_equal(tout, np.maximum(tin, 0.0, out=a), out=ws("r_through", p, bool))
        core = np.greater_equal(cout, np.maximum(cin, 0.0, out=a), out=ws("r_core", p, bool))
        core &= through
        before = np.less_equal(tin, 1.0, out=ws("r_before", p, bool))
        flag = ws("r_flag", p, bool)
        inside = np.less_equal(1.0, tout, out=ws("r_inside", p, bool))
        inside &= before
        inside &= through
        occluded = np.less(1.0, tin, out=ws("r_occluded", p, bool))
        occluded &= through
        stop = np.less_equal(1.0, cout, out=ws("r_stop", p, bool))
        stop &= core
        stop &= before
        passed = np.greater(1.0, cout, out=flag)
        passed &= core
    out = []
    for mask in (inside, occluded, stop, passed, through):
        full = np.zeros(n)
        full[boxes_idx] = _segment_counts(mask, box_ends)
        out.append(full)
    return tuple(out)


def _expected_beams(boxes: Boxes, sensor: SensorModel, az_lo, az_hi, el_lo, el_hi, judged,
                    table: _BoxTable | None = None, ws: Scratch | None = None) -> np.ndarray:
    """Beams of the sensor model (rings x azimuth steps) whose rays hit each box.

    The beams of a box are a (ring, column) grid: one row per (box, ring), the columns padded
    to the widest box's (at most :data:`EXPECTED_COLUMNS`), so the trigonometry and the box
    rotation broadcast over rows and columns (no per-beam gathers); padding columns do not
    count. Same arithmetic, beam for beam, as a per-beam computation."""
    ws = ws or _SCRATCH
    out = np.zeros(len(boxes))
    rings, ring_cos, ring_sin = _ring_table(sensor)
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
    rows = int(n_ring.sum())
    if not rows:
        return out
    width = int(n_az.max())
    column = np.arange(width)
    azimuth = az_lo[idx][:, None] + (column + 0.5) * step * stretch[:, None]  # (boxes, columns)
    cos_az, sin_az = np.cos(azimuth), np.sin(azimuth)
    row_box = np.repeat(np.arange(len(idx)), n_ring)  # one row per (box, ring)
    ring = np.repeat(r_lo, n_ring) + positions_in_runs(n_ring)
    ce = ring_cos[ring][:, None]
    box = idx[row_box]
    c, s = table.cos[box][:, None], table.sin[box][:, None]

    def grid(name: str) -> np.ndarray:
        return ws(name, rows * width, np.float64).reshape(rows, width)

    dx = np.multiply(ce, cos_az.take(row_box, axis=0, out=grid("e_x"), mode="clip"), out=grid("e_x"))
    dy = np.multiply(ce, sin_az.take(row_box, axis=0, out=grid("e_y"), mode="clip"), out=grid("e_y"))
    t1, t2, tmp = grid("e_t1"), grid("e_t2"), grid("e_tmp")
    lx = np.multiply(c, dx, out=grid("e_lx"))
    lx += np.multiply(s, dy, out=tmp)
    ly = np.multiply(c, dy, out=grid("e_ly"))
    ly -= np.multiply(s, dx, out=tmp)
    direction = (lx, ly, ring_sin[ring][:, None])
    tmin = tmax = None
    with np.errstate(divide="ignore", invalid="ignore"):
        for axis in range(3):
            inv = np.divide(1.0, direction[axis], out=direction[axis])
            np.multiply(table.body[0][box, axis][:, None], inv, out=t1)
            np.multiply(table.body[1][box, axis][:, None], inv, out=t2)
            if tmin is None:
                tmin, tmax = np.minimum(t1, t2, out=dx), np.maximum(t1, t2, out=dy)
            else:
                np.fmax(tmin, np.minimum(t1, t2, out=tmp), out=tmin)
                np.fmin(tmax, np.maximum(t1, t2, out=t1), out=tmax)
    hit = ws("e_hit", rows * width, bool).reshape(rows, width)
    np.greater_equal(tmax, np.maximum(tmin, 0.0, out=tmp), out=hit)
    hit &= column < n_az[row_box][:, None]
    per_box = np.bincount(row_box, weights=np.count_nonzero(hit, axis=1), minlength=len(idx))
    out[idx] = per_box * stretch
    return out


def _ground(x, y, z, boxes: Boxes, reach: float, quantile: float, ws: Scratch | None = None) -> np.ndarray:
    """:func:`local_ground` on the scan's coordinate columns (contiguous, one dtype)."""
    ws = ws or _SCRATCH
    n = len(boxes)
    out = np.full(n, np.nan)
    bottom = boxes.center[:, 2] - boxes.size[:, 2] / 2
    centre, size = boxes.center.copy(), boxes.size.copy()
    centre[:, 2] = bottom - 1.0
    size[:, :2] += 2 * reach
    size[:, 2] = 4.0
    wide = Boxes(centre, size, boxes.yaw)
    if not wide.valid_mask().all():
        wide.validate()
    if not len(x):
        return out
    dt = x.dtype.type
    half = wide.size / 2.0
    # The test of a point against a box runs in the scan's precision, on box-relative x / y,
    # the z bounds rounded outward (as geometry.boxes.points_in_boxes, which this reproduces).
    zlo = round_up_to(wide.center[:, 2] - half[:, 2], dt)
    zhi = round_down_to(wide.center[:, 2] + half[:, 2], dt)
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
    local = positions_in_runs(per_box)
    gx = c0[box_of, 0] + local // extent[box_of, 1]
    gy = c0[box_of, 1] + local % extent[box_of, 1]
    ccx, ccy, _ = to_box_local(origin[0] + (gx + 0.5) * cell, origin[1] + (gy + 0.5) * cell, 0.0,
                               wide.center[box_of, 0], wide.center[box_of, 1], 0.0, cos64[box_of], sin64[box_of])
    grow = cell * np.sqrt(0.5) + _GROUND_SLACK
    touch = (np.abs(ccx) <= half[box_of, 0] + grow) & (np.abs(ccy) <= half[box_of, 1] + grow)
    box_of, key = box_of[touch], gx[touch] * ny + gy[touch]  # box-major, cells ascending
    # The points: in a cell some box lists and within the boxes' union z range, sorted by cell
    # (radix). Off-grid points (and NaN) clamp into the grid's two-cell border, which no box
    # lists.
    m = len(x)
    listed = np.zeros(nx * ny, dtype=bool)
    listed[key] = True
    with np.errstate(invalid="ignore"):
        f = ws("g_f", m, dt)
        cell_key, column = ws("g_cell", m, np.int16), ws("g_column", m, np.int16)
        for coordinate, offset, count, index in ((x, origin[0], nx, cell_key), (y, origin[1], ny, column)):
            np.subtract(coordinate, dt(offset), out=f)
            f *= dt(1.0 / cell)
            _clamp(f, count - 1, ws("g_nan", m, bool))  # NaN -> 0
            np.copyto(index, f, casting="unsafe")  # truncation: the floor of these non-negative values
        cell_key *= np.int16(ny)
        cell_key += column
        ok = listed.take(cell_key, out=ws("g_ok", m, bool), mode="clip")
        flag = ws("g_flag", m, bool)
        ok &= np.greater_equal(z, zlo.min(), out=flag)
        ok &= np.less_equal(z, zhi.max(), out=flag)
    pts = ws.nonzero(ok, "g_pts")
    k = len(pts)
    if not k:
        return out
    pkey = cell_key.take(pts, out=ws("g_key", k, np.int16), mode="clip")
    order = np.argsort(pkey, kind="stable")
    ordered = pkey.take(order, out=ws("g_key_sorted", k, np.int16), mode="clip")
    pts = pts.take(order, out=ws("g_sorted", k, np.int64), mode="clip")
    del order
    # A box's consecutive cells are one run of the sorted points.
    if len(key):
        new = np.ones(len(key), dtype=bool)
        new[1:] = (np.diff(key) != 1) | (np.diff(box_of) != 0)
        first = np.flatnonzero(new)
        last = np.empty_like(first)
        last[:-1] = first[1:] - 1
        last[-1] = len(key) - 1
        # the run's bounds in the sorted points by binary search (int16 queries: no conversion)
        run_lo = np.searchsorted(ordered, key[first].astype(np.int16), side="left")
        run_hi = np.searchsorted(ordered, key[last].astype(np.int16), side="right")
        run_box = box_of[first]
    else:
        run_lo = run_hi = run_box = np.zeros(0, np.int64)
    length = run_hi - run_lo
    pair = ws.runs(run_lo, length, "g_pair")
    q = len(pair)
    box_pairs = np.bincount(run_box, weights=length, minlength=n).astype(np.int64)
    pair = pts.take(pair, out=ws("g_pair_scan", q, np.int64), mode="clip")  # positions in the scan
    px, py, pz = (a.take(pair, out=ws(name, q, dt), mode="clip") for a, name in ((x, "g_px"), (y, "g_py"),
                                                                                   (z, "g_pz")))
    a, b = ws("g_a", q, dt), ws("g_b", q, dt)

    def rep(values: np.ndarray) -> np.ndarray:
        return np.repeat(values, box_pairs)  # a transient array (cheaper than a gather)

    keep = np.greater_equal(pz, rep(zlo), out=ws("g_keep", q, bool))
    flag = ws("g_qflag", q, bool)
    keep &= np.less_equal(pz, rep(zhi), out=flag)
    px -= rep(cx)  # dx
    py -= rep(cy)  # dy
    cb, sb = rep(c), rep(s)
    lx = np.multiply(cb, px, out=a)
    lx += np.multiply(sb, py, out=b)
    ly = np.multiply(cb, py, out=cb)
    ly -= np.multiply(sb, px, out=b)
    keep &= np.less_equal(np.abs(lx, out=lx), rep(hl), out=flag)
    keep &= np.less_equal(np.abs(ly, out=ly), rep(hw), out=flag)
    # Non-members read +inf: the k-th smallest of a box's run is its k-th smallest member for
    # every k below its member count (no compaction of the pairs).
    np.copyto(pz, dt(np.inf), where=np.logical_not(keep, out=flag))
    ends = np.cumsum(box_pairs)
    members = _segment_counts(keep, ends)
    judged = np.flatnonzero(members)
    out[judged] = run_quantiles(pz, keep, ends, members, quantile, ws)[judged]
    return out


#: Stride of the sample :func:`run_quantiles` takes its thresholds from.
SAMPLE_STRIDE = 8


def run_quantiles(values, member, ends, members, quantile: float, ws: Scratch | None = None) -> np.ndarray:
    """Per run of ``values`` (laid end to end, ending at ``ends``; the non-``member`` values
    +inf) with ``members`` > 0: its ``int(quantile * (members - 1))``-th smallest value, what
    ``np.partition`` of the whole run gives (NaN for runs without members).

    A threshold per run from every :data:`SAMPLE_STRIDE`-th value (about twice the wanted
    rank in the sample), then the positions of the values below it (one pass; a run's count by
    binary search at its end): when the wanted rank falls among them, only those values (a
    small share) are partitioned; otherwise a count of the values at the threshold (a second
    pass, only then): when the rank falls among the values equal to it (flat ground), that is
    the answer; else (a sample that missed, rare) the whole run. Exact in every case."""
    ws = ws or _SCRATCH
    n = len(ends)
    starts = ends - np.diff(ends, prepend=0)
    rank = (quantile * (members - 1).astype(np.float64)).astype(np.int64)  # int(): truncation
    threshold = np.full(n, np.inf)
    bounds = list(zip(starts.tolist(), ends.tolist()))
    for b in np.flatnonzero(members).tolist():  # one small partial sort per box (boxes, not points)
        lo, hi = bounds[b]
        sampled = int(np.count_nonzero(member[lo:hi:SAMPLE_STRIDE]))
        if sampled:
            k = min(2 * int(quantile * (sampled - 1)) + 2, sampled - 1)
            threshold[b] = np.partition(values[lo:hi:SAMPLE_STRIDE], k)[k]
    dt = values.dtype.type
    lengths = ends - starts
    limit = np.repeat(threshold.astype(dt), lengths)
    q = len(values)
    below = ws.nonzero(np.less(values, limit, out=ws("q_below", q, bool)), "q_below_idx")  # members only (+inf others)
    chosen_end = np.searchsorted(below, ends)  # the values under the threshold, run by run
    under = chosen_end.copy()
    under[1:] -= chosen_end[:-1]
    out = np.full(n, np.nan)
    finite = np.isfinite(threshold)
    # the count at the threshold only where the wanted rank is not under it (flat ground)
    flat = finite & (under <= rank)
    if flat.any():
        flat &= rank < _segment_counts(np.less_equal(values, limit, out=ws("q_at", q, bool)), ends)
    out[flat] = threshold[flat]
    chosen = values.take(below, mode="clip")  # run by run
    for b in np.flatnonzero(finite & (rank < under)).tolist():
        part = chosen[chosen_end[b] - under[b]:chosen_end[b]]
        out[b] = np.partition(part, rank[b])[rank[b]]
    for b in np.flatnonzero((members > 0) & ~flat & ~(finite & (rank < under))).tolist():  # the sample missed
        lo, hi = bounds[b]
        out[b] = np.partition(values[lo:hi], rank[b])[rank[b]]
    return out


def _columns(points: np.ndarray, ws: Scratch | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Contiguous x, y, z columns in the scan's precision (float32 stays float32, others
    become float64): numpy's SIMD loops skip strided arrays."""
    ws = ws or _SCRATCH
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] < 3:
        raise DataError(f"points must be (N, >=3), got shape {points.shape}")
    dt = np.float32 if points.dtype == np.float32 else np.float64
    out = []
    for k, name in enumerate(("x", "y", "z")):
        column = ws(name, len(points), dt)
        np.copyto(column, points[:, k], casting="unsafe")
        out.append(column)
    return tuple(out)


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
_SIDE_POOL_LOCK = threading.Lock()


def _side_pool() -> ThreadPoolExecutor:
    """The filter's second thread, made on first use (under a lock: two pipelines' first frames
    at once must not each make one and leak the other's idle thread)."""
    global _SIDE_POOL
    with _SIDE_POOL_LOCK:
        if _SIDE_POOL is None:
            _SIDE_POOL = ThreadPoolExecutor(max_workers=1, thread_name_prefix="pcc-filter")
        return _SIDE_POOL


def evidence(points: np.ndarray, boxes: Boxes, sensor: SensorModel | None = None, workers: int = 1) -> Evidence:
    """Free-space, return-count and ground-contact measurements of every box, from the scan.

    The sensor sits at the scan frame's origin (true for a scan in its own sensor frame).
    Vectorised over (ray, box) pairs generated box by box: no loop over points or boxes; the
    pairs' geometry runs column by column in float64 on per-box values repeated over each
    box's run. ``workers`` >= 2: the local ground (a query of its own over the scan) and the
    sensor model's expected returns (about 40 % of the work at 20 cars) are measured on a second
    thread while this one follows the rays (numpy releases the GIL in its loops); the values are
    the same either way.
    """
    sensor = sensor or SensorModel()
    n = len(boxes)
    zero = np.zeros(n)
    if n == 0:
        return Evidence(*([zero] * 7), _derive(*([zero] * 7), boxes))
    if not boxes.valid_mask().all():
        boxes.validate()  # DataError naming the box
    x, y, z = _columns(points)
    pool = _side_pool() if workers > 1 else None
    # The side thread's jobs, in order: the ground (it needs only the scan and the boxes, so it
    # starts before the box-level setup below), then the expected returns; the two take about
    # as long as the rays do here.
    ground_job = pool.submit(_ground, x, y, z, boxes, GROUND_REACH, 0.05, _SCRATCH) if pool else None
    window = angular_window(boxes)
    table = _BoxTable(boxes)
    expected_job = pool.submit(_expected_beams, boxes, sensor, *window, table=table, ws=_SCRATCH) if pool else None
    n_in, n_occ, n_stop, n_pass, n_rays = _ray_counts(x, y, z, boxes, table, window, _SCRATCH)
    if pool:
        ground, expected = ground_job.result(), expected_job.result()
    else:
        ground = _ground(x, y, z, boxes, GROUND_REACH, 0.05, _SCRATCH)
        expected = _expected_beams(boxes, sensor, *window, table=table, ws=_SCRATCH)
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
