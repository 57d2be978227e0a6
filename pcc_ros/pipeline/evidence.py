"""The evidence filter's measurements in the scan: rays towards every box, the sensor model's
expected returns, the local ground (the physics behind :mod:`pcc_ros.pipeline.filter`'s
``density``, ``free_space``, ``through`` and ``ground_gap`` terms; definitions in ``docs/filter.md``).

Numpy passes over the scan (in its own precision: float32 for sensor data) and over the boxes
build the index structures (which points each box looks at); the (ray, box), (point, box) and
(beam, box) pairs are then visited box by box in the compiled kernels of
:mod:`pcc_ros.pipeline.evidence_kernels` (numba, imported on first use; :func:`warm_up`
compiles them). The ray geometry that decides a pair runs in float64 with the same operations,
operand for operand, as the 93cd59e code kept in ``benchmarks/_reference.py`` (``pcc bench
filter`` checks the outputs bit-identical).
"""

from __future__ import annotations

import contextvars
import threading
from collections.abc import Collection
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from functools import lru_cache, partial

import numpy as np

from pcc_ros.errors import DataError
from pcc_ros.geometry.beams import SENSOR_PRESETS, SensorModel
from pcc_ros.geometry.boxes import box_corners, round_down_to, round_up_to
from pcc_ros.geometry.canonical import to_box_local
from pcc_ros.pipeline.evidence_index import BevIndex, Footprints, bev_index
from pcc_ros.scratch import Scratch
from pcc_ros.types import Boxes


@lru_cache(maxsize=16)
def _ring_table(sensor: SensorModel) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``sensor.ring_elevations()`` with their cosines and sines, computed once per sensor
    model (about 90 us a call: a constant of the frame loop); read-only."""
    rings = sensor.ring_elevations()
    table = (rings, np.cos(rings), np.sin(rings))
    for values in table:
        values.flags.writeable = False
    return table


#: The solid core of a car body inside its box, as fractions of the box (length, width) and of
#: its height from the bottom: below the windows, above the gap under the chassis. Rays that
#: cross this core and return from beyond it say the box is empty.
CORE_FRACTION = (0.8, 0.8)
CORE_Z = (0.2, 0.6)
#: Where no ring of the beam model crosses that band over the core's footprint (a sparse
#: sensor's rings fall metres apart at range), the core is the cabin instead: up to this
#: fraction of the box height, over the central :data:`CABIN_FRACTION` of its length (a car's
#: roof and pillars stand there; over the hood and the boot the top of a car's box is air).
#: Without it such a box has no ray through its core: no free-space evidence either way.
CORE_Z_OPEN = 1.0
CABIN_FRACTION = 0.3
#: Returns lower than this above the box bottom are ground (counted as passing, not as car).
EVIDENCE_GROUND = 0.3
#: The local ground is the 5 % quantile of the heights of the returns within this many metres
#: of the box footprint (all around it: the returns beside a car reach the ground it hides).
GROUND_REACH = 3.0
#: ... widened where the beam model's rings fall farther apart on the ground (far boxes, sparse
#: sensors): half the ring spacing at the box's range, at most this many metres.
GROUND_REACH_MAX = 10.0
#: ``cover`` of a car: the median share of a true car box's unhidden azimuth columns holding
#: a return (seed-11 SynthCars, every simulated sensor), and the number of such prior columns
#: the term starts from (chosen by leave-one-sensor-out cross-validation, docs/filter.md).
COVER_PRIOR = 1.0
COVER_PRIOR_COLUMNS = 120.0
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
    profile: dict[str, np.ndarray] = field(default_factory=dict)  # the profile terms asked for

    def as_dict(self) -> dict[str, np.ndarray]:
        names = ("n_in", "n_stop", "n_pass", "n_occluded", "n_rays", "expected", "ground_z")
        raw = {k: getattr(self, k) for k in names}
        return {**raw, **self.terms}


def core_rings(boxes: Boxes, sensor: SensorModel, band: tuple[float, float] = CORE_Z) -> np.ndarray:
    """How many of the beam model's rings cross each box's height ``band`` (fractions of the box
    height from its bottom) somewhere over its core footprint: a ring of elevation ``e`` meets
    the heights ``d tan e`` at the horizontal ranges ``d`` of the core, from its nearest to its
    farthest point (the centre's range less / plus the core's half diagonal). The sensor sits at
    the scan frame's origin, the boxes upright (yaw only)."""
    slope = np.tan(_ring_table(sensor)[0])
    d = np.hypot(boxes.center[:, 0], boxes.center[:, 1])
    reach = np.hypot(*(boxes.size[:, :2] * np.array(CORE_FRACTION)).T) / 2
    bottom, height = boxes.center[:, 2] - boxes.size[:, 2] / 2, boxes.size[:, 2]
    near = np.maximum(d - reach, 0.1)[:, None] * slope
    far = (d + reach)[:, None] * slope
    lo, hi = (bottom + band[0] * height)[:, None], (bottom + band[1] * height)[:, None]
    return ((np.maximum(near, far) >= lo) & (np.minimum(near, far) <= hi)).sum(axis=1)


def core_box(boxes: Boxes, sensor: SensorModel | None) -> tuple[np.ndarray, np.ndarray]:
    """Each box's core, ``(lo, hi)`` corners in its own frame (centre at 0): the ``CORE_FRACTION``
    x ``CORE_Z`` body band, or the cabin (:data:`CABIN_FRACTION` of the length, up to
    :data:`CORE_Z_OPEN` of the height) where no ring of ``sensor`` crosses that band
    (:func:`core_rings`; ``None``: no beam model, the band as it is). A VLP-16's rings lie 2 deg
    apart, 0.7 m at 20 m: an empty car-sized box there is often crossed above its band only, and
    with the band alone it read ``free_space`` 0, as a car does that nothing shows."""
    half = boxes.size / 2
    scale = np.array([CORE_FRACTION[0], CORE_FRACTION[1], 1.0])
    lo, hi = -half * scale, half * scale
    lo[:, 2] = -half[:, 2] + CORE_Z[0] * 2 * half[:, 2]
    hi[:, 2] = -half[:, 2] + CORE_Z[1] * 2 * half[:, 2]
    if sensor is not None and len(boxes):
        cabin = core_rings(boxes, sensor) == 0
        hi[cabin, 0] = half[cabin, 0] * CABIN_FRACTION
        lo[cabin, 0] = -hi[cabin, 0]
        hi[cabin, 2] = -half[cabin, 2] + CORE_Z_OPEN * 2 * half[cabin, 2]
    return lo, hi


class _BoxTable:
    """Per-box values of the ray geometry, computed once per frame (every value is the one a
    per-pair computation would give: same operands, same order)."""

    def __init__(self, boxes: Boxes, sensor: SensorModel | None = None) -> None:
        self.cos, self.sin = np.cos(boxes.yaw), np.sin(boxes.yaw)
        # the kernels' argument: C order, aligned, writable whatever the caller's array (a
        # read-only or unaligned one, e.g. over a message buffer, is another numba signature: a
        # compilation of seconds in the middle of a run)
        self.center = np.require(boxes.center, np.float64, ["C", "A", "W"])
        cx, cy, cz = boxes.center.T
        # the sensor (the scan frame's origin) in each box's frame
        self.origin = np.stack(to_box_local(0.0, 0.0, 0.0, cx, cy, cz, self.cos, self.sin), axis=1)
        half = boxes.size / 2
        body_lo, body_hi = -half.copy(), half.copy()
        body_lo[:, 2] += EVIDENCE_GROUND
        core_lo, core_hi = core_box(boxes, sensor)
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


def _ray_counts(x, y, z, boxes: Boxes, table: _BoxTable, window, ws: Scratch,
                column_step: float | None = None) -> tuple[np.ndarray, ...]:
    """``n_in, n_occluded, n_stop, n_pass, n_rays`` of every box (float64), and with
    ``column_step`` (radians: the beam model's azimuth step) ``n_filled, n_seen``: the box's
    azimuth columns of that step holding an in-box return, and those holding one or a ray
    through the core that returned from beyond it (the columns not hidden by something in front).

    The ray index: numpy's SIMD ``arctan2`` and one compiled pass over the scan, both in its
    own precision, give every point's cell, its azimuth bin and slope band (the slope ``z / r``
    is monotone in elevation: no elevation ``arctan2`` per point); a counting sort groups the
    points of the cells some judged box searches (its azimuth sector widened by one bin each way, the bands
    of its slope window); the compiled kernel then visits each box's cells, tests the box's
    slope window (with a slack far above float32 rounding: a superset of the rays that reach the
    box) and runs the exact float64 slab tests. Non-finite points never count.
    """
    n = len(boxes)
    out = np.zeros((n, 5))
    cols = np.zeros((n if column_step else 0, 2))
    az_lo, az_hi, el_lo, el_hi, judged = window
    boxes_idx = np.flatnonzero(judged)
    m = len(boxes_idx)
    if not m or not len(x):
        return (*out.T.copy(), *cols.T.copy())
    dt = x.dtype.type
    # Windows in slope space, widened by the slack; bands span the boxes' windows.
    s_lo = np.tan(el_lo[boxes_idx]) - _SLOPE_SLACK * (1.0 + np.tan(el_lo[boxes_idx]) ** 2)
    s_hi = np.tan(el_hi[boxes_idx]) + _SLOPE_SLACK * (1.0 + np.tan(el_hi[boxes_idx]) ** 2)
    e0 = float(s_lo.min())
    width = max(float(s_hi.max()) - e0, 1e-6) / _EL_BANDS
    b0 = np.floor((az_lo[boxes_idx] + np.pi) * (_AZ_BINS / (2 * np.pi))).astype(np.int64) - 1
    b1 = np.floor((az_hi[boxes_idx] + np.pi) * (_AZ_BINS / (2 * np.pi))).astype(np.int64) + 1
    nbins = np.minimum(b1 - b0 + 1, _AZ_BINS)
    band_lo = np.clip(np.floor((s_lo - e0) / width).astype(np.int64), 1, _EL_BANDS)  # one band wider below
    band_hi = np.clip(np.floor((s_hi - e0) / width).astype(np.int64) + 2, 1, _EL_BANDS)  # and above
    from pcc_ros.pipeline import evidence_kernels as kernels  # numba: heavy, only when measuring

    cells, n_bins = _AZ_BINS * (_EL_BANDS + 2), int(nbins.sum())
    first_cell, last_cell = ws("first_cell", n_bins, np.int64), ws("last_cell", n_bins, np.int64)
    bin_ends, wanted = np.empty(m, np.int64), np.zeros(cells, dtype=bool)
    kernels.ray_cells(b0, nbins, band_lo, band_hi, _AZ_BINS, _EL_BANDS + 2, first_cell, last_cell, bin_ends, wanted)
    p = len(x)
    with np.errstate(invalid="ignore"):
        azimuth = np.arctan2(y, x, out=ws("az", p, dt))  # numpy's SIMD pass
    # A return at the sensor (0, 0, 0) has slope 0, as arctan2(0, 0) = 0 (the 93cd59e index
    # paired it with the boxes at azimuth and elevation 0); straight up / down is beyond every
    # box's window (a slope of +-inf, or huge: its band clamps); NaN points get cell 0 (no box).
    key, slope = ws("key", p, np.int16), ws("slope", p, dt)
    kernels.ray_keys(azimuth, x, y, z, _AZ_BINS, _EL_BANDS, e0, 1.0 / width, key, slope)
    start, order = ws("start", cells + 1, np.int64), ws("order", p, np.int64)
    kernels.counting_sort(key, wanted, start, order)
    kernels.ray_counts(x, y, z, slope, order, start, first_cell, last_cell, bin_ends, boxes_idx,
                       s_lo.astype(dt), s_hi.astype(dt), table.center, table.cos, table.sin,
                       table.origin, *table.body, *table.core, out, azimuth,
                       *_column_grid(window, boxes_idx, column_step), cols)
    return (*out.T.copy(), *cols.T.copy())


def _column_grid(window, boxes_idx: np.ndarray, step: float | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per judged box, the azimuth columns of ``step`` radians over its azimuth interval: the
    first column's start, columns per radian, the column count (one column without a step)."""
    az_lo, az_hi = window[0][boxes_idx], window[1][boxes_idx]
    if not step:
        return az_lo, np.ones(len(boxes_idx)), np.ones(len(boxes_idx), dtype=np.int64)
    count = np.floor((az_hi - az_lo) / step).astype(np.int64) + 1
    return az_lo, np.full(len(boxes_idx), 1.0 / step), count


def _expected_beams(boxes: Boxes, sensor: SensorModel, az_lo, az_hi, el_lo, el_hi, judged,
                    table: _BoxTable | None = None) -> np.ndarray:
    """Beams of the sensor model (rings x azimuth steps) whose rays hit each box.

    The beams of a box are a (ring, column) grid: the columns' directions (at most
    :data:`EXPECTED_COLUMNS` per box) are one (boxes, columns) table of cosines and sines, and
    the compiled kernel runs the slab test of every (ring, column) beam of each box."""
    out = np.zeros(len(boxes))
    rings, rings_cos, rings_sin = _ring_table(sensor)
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
    column = np.arange(int(n_az.max()))
    azimuth = az_lo[idx][:, None] + (column + 0.5) * step * stretch[:, None]  # (boxes, columns)
    from pcc_ros.pipeline import evidence_kernels as kernels  # numba: heavy, only when measuring

    counts = np.zeros(len(idx))
    kernels.expected_counts(idx, r_lo, n_ring, n_az, rings_cos, rings_sin, np.cos(azimuth), np.sin(azimuth),
                            table.cos, table.sin, *table.body, counts)
    out[idx] = counts * stretch
    return out


def ground_query(boxes: Boxes, reach, dt: type) -> tuple[Footprints, tuple[np.ndarray, ...]]:
    """The local ground's boxes (each box widened by ``reach`` around its footprint, from 3 m
    below to 1 m above its bottom) as the scan index sees them, and their exact test's values in
    the scan's precision ``dt``: ``(zlo, zhi, cx, cy, cos, sin, half length, half width)``."""
    bottom = boxes.center[:, 2] - boxes.size[:, 2] / 2
    centre, size = boxes.center.copy(), boxes.size.copy()
    centre[:, 2] = bottom - 1.0
    size[:, :2] += 2 * np.reshape(reach, (-1, 1))
    size[:, 2] = 4.0
    wide = Boxes(centre, size, boxes.yaw)
    if not wide.valid_mask().all():
        wide.validate()
    half = wide.size / 2.0
    # The test of a point against a box runs in the scan's precision, on box-relative x / y,
    # the z bounds rounded outward (as geometry.boxes.points_in_boxes, which this reproduces).
    zlo = round_up_to(wide.center[:, 2] - half[:, 2], dt)
    zhi = round_down_to(wide.center[:, 2] + half[:, 2], dt)
    cos64, sin64 = np.cos(wide.yaw), np.sin(wide.yaw)
    test = (zlo, zhi, wide.center[:, 0].astype(dt), wide.center[:, 1].astype(dt), cos64.astype(dt),
            sin64.astype(dt), half[:, 0].astype(dt), half[:, 1].astype(dt))
    footprints = Footprints(wide.center[:, 0], wide.center[:, 1], cos64, sin64, half[:, 0], half[:, 1],
                            float(zlo.min()), float(zhi.max()))
    return footprints, test


def ground_heights(x, y, z, index: BevIndex, runs, test: tuple[np.ndarray, ...], quantile: float,
                   ws: Scratch) -> np.ndarray:
    """Each box's ``quantile`` of the heights of the points its exact ``test`` (:func:`ground_query`)
    accepts among the candidates of its cell ``runs`` in ``index`` (NaN: none)."""
    from pcc_ros.pipeline import evidence_kernels as kernels  # numba: heavy, only when measuring

    out = np.full(len(test[0]), np.nan)
    dt = x.dtype.type
    kernels.ground_quantiles(x, y, z, index.order, index.start, *runs, *test, float(quantile),
                             ws("g_values", len(x), dt), ws("g_spare", len(x), dt), out)
    return out


def _ground(x, y, z, boxes: Boxes, reach: float, quantile: float, ws: Scratch | None = None) -> np.ndarray:
    """:func:`local_ground` on the scan's coordinate columns (contiguous, one dtype): its own
    index of the scan (:mod:`pcc_ros.pipeline.evidence_index`)."""
    ws = ws or _SCRATCH
    footprints, test = ground_query(boxes, reach, x.dtype.type)
    if not len(x):
        return np.full(len(boxes), np.nan)
    index = bev_index(x, y, z, [footprints], ws)
    return ground_heights(x, y, z, index, index.runs[0], test, quantile, ws)


def ground_reach(boxes: Boxes, sensor: SensorModel) -> np.ndarray:
    """Metres around each box's footprint the local ground looks: :data:`GROUND_REACH`, or half
    the spacing on the road of the sensor's two rings either side of the box's range when that
    is wider, up to :data:`GROUND_REACH_MAX`. A sparse sensor's rings meet the road metres apart
    at range, and a fixed reach would often find no ground return at all (the term then says
    nothing). The road is taken at the box bottom, the sensor at the origin."""
    if not len(boxes):
        return np.zeros(0)
    rings = _ring_table(sensor)[0]
    d = np.maximum(np.hypot(boxes.center[:, 0], boxes.center[:, 1]), 1.0)
    h = np.maximum(boxes.size[:, 2] / 2 - boxes.center[:, 2], 0.3)  # sensor height above the box bottom
    seen = -np.arctan2(h, d)  # elevation at which the ground under the box is seen
    i = np.clip(np.searchsorted(rings, seen), 1, len(rings) - 1)
    shallow, steep = -rings[i], -rings[i - 1]  # the rings either side, as depression angles
    with np.errstate(divide="ignore", invalid="ignore"):
        spacing = np.where(shallow > 0, h / np.tan(np.maximum(shallow, 1e-9)) - h / np.tan(steep), np.inf)
    return np.clip(spacing / 2, GROUND_REACH, GROUND_REACH_MAX)


def _columns(points: np.ndarray, ws: Scratch | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Contiguous x, y, z columns in the scan's precision (float32 stays float32, others
    become float64): numpy's SIMD loops skip strided arrays."""
    ws = ws or _SCRATCH
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] < 3:
        raise DataError(f"points must be (N, >=3), got shape {points.shape}")
    dt = np.float32 if points.dtype == np.float32 else np.float64
    columns = ws("xyz", 3 * len(points), dt).reshape(3, len(points))
    np.copyto(columns, points[:, :3].T, casting="unsafe")  # one pass over the scan's rows
    return columns[0], columns[1], columns[2]


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


def beside(fn, *args) -> Future:
    """``fn(*args)`` submitted to the filter's second thread (in a copy of this thread's context:
    a line logged there is the calling node's): its future. The thread's jobs run in order."""
    return _side_pool().submit(contextvars.copy_context().run, fn, *args)


def evidence(points: np.ndarray, boxes: Boxes, sensor: SensorModel | None = None, workers: int = 1,
             reach: float | np.ndarray | None = None, rays: bool = True, expected: bool = True,
             ground: bool = True, columns: bool = False, profile: Collection[str] = ()) -> Evidence:
    """Free-space, return-count and ground-contact measurements of every box, from the scan.

    The sensor sits at the scan frame's origin (true for a scan in its own sensor frame).
    Numpy passes index the scan; compiled kernels visit each box's candidate rays, points and
    beams. ``workers`` >= 2: the footprint queries (the local ground and the profile pass, over
    one BEV index of the scan) and the sensor model's expected returns are measured on a second
    thread while this one follows the rays (the kernels release the GIL); the values are the same
    either way.
    ``reach``: metres around each footprint the local ground looks (default
    :func:`ground_reach` of the sensor model; ``GROUND_REACH`` is the fixed reach of 93cd59e).
    ``rays`` / ``expected`` / ``ground`` False: that measurement is skipped (its raw values and
    the terms that need them are NaN; the others are the same values): a rule whose weights
    leave a term out does not pay for it (``rays``: n_in, n_stop, n_pass, n_occluded, n_rays;
    ``density`` and ``through`` need rays and expected, ``free_space`` rays, ``ground_gap`` ground).
    ``columns`` (with ``rays``): also the azimuth columns behind ``cover`` (``n_filled``, ``n_seen``
    and ``cover`` in the terms; :func:`cover`). ``profile``: the profile terms to measure too
    (:func:`pcc_ros.pipeline.evidence_profile.profile_terms`' values, in :attr:`Evidence.profile`).
    """
    sensor = sensor or SENSOR_PRESETS["hdl64"]
    n = len(boxes)
    zero = np.zeros(n)
    profile = set(profile)
    if n == 0:
        return Evidence(*([zero] * 7), _derive(*([zero] * 7), boxes), _footprint_measures(
            zero, zero, zero, boxes, sensor, False, None, profile, _SCRATCH)[1])
    if not boxes.valid_mask().all():
        boxes.validate()  # DataError naming the box
    x, y, z = _columns(points)
    nan = np.full(n, np.nan)
    footprints = ground or bool(profile)
    # A second thread only when the work splits: the rays here, the rest there.
    pool = workers > 1 and rays and (footprints or expected)
    # The side thread's jobs, in order: the footprint queries (they need only the scan and the
    # boxes, so they start before the box-level setup below), then the expected returns; the
    # rays here take about as long (20 cars, the shipped rule's profile pass among the queries).
    footprint_job = beside(_footprint_measures, x, y, z, boxes, sensor, ground, reach, profile,
                           _SCRATCH) if pool and footprints else None
    window = angular_window(boxes) if rays or expected else None
    table = _BoxTable(boxes, sensor) if rays or expected else None
    expected_job = beside(partial(_expected_beams, table=table), boxes, sensor, *window) \
        if pool and expected else None
    cover_terms = {}
    if rays:
        step = np.deg2rad(sensor.azimuth_resolution_deg) if columns else None
        n_in, n_occ, n_stop, n_pass, n_rays, *col = _ray_counts(x, y, z, boxes, table, window, _SCRATCH, step)
        if columns:
            cover_terms = {"n_filled": col[0], "n_seen": col[1], "cover": cover(*col)}
    else:
        n_in, n_occ, n_stop, n_pass, n_rays = nan, nan, nan, nan, nan
    expected = (expected_job.result() if expected_job else _expected_beams(boxes, sensor, *window, table=table)) \
        if expected else nan
    ground, profile_out = footprint_job.result() if footprint_job else \
        _footprint_measures(x, y, z, boxes, sensor, ground, reach, profile, _SCRATCH) if footprints \
        else (nan, {})
    return Evidence(
        n_in, n_stop, n_pass, n_occ, n_rays, expected, ground,
        {**_derive(n_in, n_stop, n_pass, n_occ, n_rays, expected, ground, boxes), **cover_terms}, profile_out,
    )


def _footprint_measures(x, y, z, boxes: Boxes, sensor: SensorModel, ground: bool, reach, profile: set[str],
                        ws: Scratch) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The queries over the boxes' footprints, sharing one BEV index of the scan
    (:mod:`pcc_ros.pipeline.evidence_index`): with ``ground``, the local ground (within ``reach``;
    ``None``: :func:`ground_reach` of the sensor model; without, NaN)
    and the ``profile`` terms (:func:`pcc_ros.pipeline.evidence_profile.profile_terms`' values)."""
    from pcc_ros.pipeline.evidence_profile import ProfileQuery, terms_before_pass  # it imports this module

    dt = x.dtype.type
    queries, measured, profile_query = [], {}, None
    if ground:
        reach = ground_reach(boxes, sensor) if reach is None else reach
        ground_footprints, ground_test = ground_query(boxes, reach, dt)
        queries.append(ground_footprints)
    if profile - {"overlap"} and len(boxes):  # a pass over the scan (terms_before_pass)
        profile_query = ProfileQuery(boxes, profile, dt)
        queries.append(profile_query.footprints)
    index = bev_index(x, y, z, queries, ws) if queries and len(x) else None
    heights = np.full(len(boxes), np.nan)
    if ground and index is not None:
        heights = ground_heights(x, y, z, index, index.runs[0], ground_test, 0.05, ws)
    if profile_query is not None:
        measured = profile_query.measure(x, y, z, index, index.runs[-1] if index else None, sensor, ws)
    # the overlap last: numpy on the boxes alone, holding the GIL while the other thread is
    # likelier to be in a kernel than at its own setup
    return heights, {**terms_before_pass(boxes, profile)[0], **measured} if profile else {}


def cover(n_filled: np.ndarray, n_seen: np.ndarray) -> np.ndarray:
    """``cover``: the share of a box's unhidden azimuth columns that hold an in-box return,
    starting from :data:`COVER_PRIOR_COLUMNS` prior columns at a car's :data:`COVER_PRIOR`.

    A car fills every column of its box that nothing in front hides; a bin, a bush, a pole or a
    short wall segment in a car-sized box fills part of them, the rays beside it crossing the
    box's core to what lies behind. A column every ray of which ended in front of the box says
    nothing (an occluded car is not condemned for what it cannot show), and a far box of few
    columns keeps about a car's value until its own columns say otherwise."""
    return (n_filled + COVER_PRIOR * COVER_PRIOR_COLUMNS) / (n_seen + COVER_PRIOR_COLUMNS)


def warm_up() -> None:
    """Compile the filter's kernels for both scan precisions (numba, on first use; loaded from
    its disk cache after the first run on a machine): one tiny frame each, so a node's first
    real frame does not pay for the compilation. Idempotent and cheap once done."""
    rng = np.random.default_rng(0)
    boxes = Boxes(np.array([[10.0, 0.0, -0.8]]), np.array([[4.0, 1.8, 1.5]]), np.zeros(1))
    scan = np.c_[rng.uniform(5, 15, (64, 2)), rng.uniform(-2, 1, 64)]
    from pcc_ros.pipeline.evidence_profile import profile_terms  # the filter's other compiled pass

    for dtype in (np.float32, np.float64):
        evidence(scan.astype(dtype), boxes)
        profile_terms(scan.astype(dtype), boxes, SENSOR_PRESETS["hdl64"])


def _derive(n_in, n_stop, n_pass, n_occ, n_rays, expected, ground, boxes: Boxes) -> dict[str, np.ndarray]:
    """The dimensionless terms the score combines (documented in docs/filter.md).

    ``ground_gap`` is one-sided: how far the box bottom floats *above* the local ground. A
    local ground above the box bottom is no evidence against the box: where no beam reaches
    the road near the box (a far box, a sparse sensor, a car hidden behind others) the lowest
    returns within reach lie on kerbs, other cars or the car itself, and on the simulated
    sensors 90 % of the true cars with a gap over 0.3 m read such a "sunk" box; every real
    false KITTI box with a gap over 0.3 m floats above its ground.
    ``through``: the rays through the box's core that return from beyond it, as a share of the
    returns a car there would give (``expected * visible``): 0 for a car, whatever the sensor,
    and for a box the scan cannot see (no rays, no evidence); a car-sized box on a smaller
    object or on free ground lets a share of the sensor's beams through. Unlike ``free_space``
    (a log-odds that reads 0 on a box without rays) it grows only with the evidence."""
    visible = np.where(n_rays > 0, 1.0 - n_occ / np.maximum(n_rays, 1.0), 1.0)
    density = np.log((n_in + 1.0) / (expected * visible + 1.0))
    free_space = np.log((n_pass + 0.5) / (n_stop + 0.5))
    through = n_pass / (expected * visible + 1.0)
    bottom = boxes.center[:, 2] - boxes.size[:, 2] / 2
    gap = bottom - ground
    ground_gap = np.where(np.isfinite(gap), np.clip(gap, 0.0, 3.0), 0.0)
    return {"density": density, "free_space": free_space, "ground_gap": ground_gap, "through": through}
