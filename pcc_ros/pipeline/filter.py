"""The detection filter: is there really a car in this box?

Two rules (``FilterConfig.rule``):

``evidence`` (default) — one calibrated probability that a detection is false, from terms
measured in the scan itself (documented with their derivation in ``docs/filter.md``):

* ``density``: log of (returns in the box + 1) / (returns a car there would give + 1), the
  expectation being the sensor model's beams that hit the box (its visible cross-section at
  that range and bearing), times the share of the scan's rays towards the box that are not
  stopped in front of it (occlusion);
* ``free_space``: log-odds of the rays through the box's solid core that return from
  *beyond* it (the box is see-through: empty) against those that end inside it;
* ``ground_gap``: metres between the box bottom and the local ground (cars stand on it);
* ``score``: the detector score as a logit, after the explicit ``score_mapping``;
* ``mismatch``: TraPCC's shape mismatch (below) against the completion of ``filter_backend``
  (0 weight unless calibrated with a car-constrained backend).

``p_false = sigmoid(w_bias + sum_k w_k * term_k)``; a detection is rejected when
``p_false > reject_threshold``. Weights and threshold come from ``pcc calibrate-filter``
(logistic regression; presets in ``config/``), never set by hand. Every box is judged —
a sparse box is exactly where false detections hide.

``trapcc`` — TraPCC (paper §4.5, §5.2): each detection is completed; the mismatch between
the raw crop and its completion is measured by

* MCD (TraPCC Eq. 2): the mean squared distance from each raw point to its nearest
  completed point (canonical units, i.e. fractions of the box length), and
* 2D contour differences in the side (x-z), front (y-z) and top (x-y) views: the
  fraction of the raw crop's occupied silhouette cells that the completion's (slightly
  dilated) silhouette does not cover, averaged over the three views,

folded into one score in [0, 1): ``1 - exp(-(mcd / mcd_scale + contour / contour_scale))``.
A detection is rejected when its mismatch score is above ``match_threshold`` AND its
(mapped) detection score is below ``detection_threshold`` (0.3 / 0.5 on KITTI in the paper).

Detector scores are not always probabilities (PointRCNN gives logits): ``score_mapping``
makes the conversion explicit.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from pcc_ros.errors import ConfigError, DataError
from pcc_ros.geometry.boxes import box_corners, pairs_in_boxes
from pcc_ros.geometry.canonical import to_box_local
from pcc_ros.metrics.chamfer import nearest_distances_batch
from pcc_ros.msg.typestore import new_message
from pcc_ros.types import Boxes

SCORE_MAPPINGS = ("identity", "sigmoid")
RULES = ("evidence", "trapcc")
_VIEWS = ((0, 2), (1, 2), (0, 1))  # side (x-z), front (y-z), top (x-y)


@dataclass(frozen=True)
class FilterConfig:
    rule: str = "evidence"
    # evidence rule: logistic weights. Defaults = the KITTI preset written by `pcc calibrate-filter`
    # into config/detection_filter.yaml (a test keeps the two equal; docs/filter.md has the command).
    w_bias: float = 1.3016
    w_density: float = -0.4338
    w_free_space: float = 0.3253
    w_ground_gap: float = 2.3514
    w_score: float = -0.9236
    w_mismatch: float = 0.0
    reject_threshold: float = 0.6131
    sensor: str = "hdl64"
    filter_backend: str = ""  # completion backend of the mismatch term; "" = the pipeline's own
    # trapcc rule
    match_threshold: float = 0.3
    detection_threshold: float = 0.5
    score_mapping: str = "identity"
    mcd_scale: float = 0.0025  # canonical units squared: (5 % of the car length)^2
    contour_scale: float = 0.5
    grid_cells: int = 24
    grid_extent: float = 0.75  # canonical half-extent of the silhouette grid

    def __post_init__(self) -> None:
        if self.score_mapping not in SCORE_MAPPINGS:
            raise ConfigError(f"score_mapping must be one of {SCORE_MAPPINGS}, got {self.score_mapping!r}")
        if self.rule not in RULES:
            raise ConfigError(f"rule must be one of {RULES}, got {self.rule!r}")
        if self.sensor not in SENSOR_PRESETS:
            raise ConfigError(f"sensor must be one of {sorted(SENSOR_PRESETS)}, got {self.sensor!r}")
        if not (self.mcd_scale > 0 and self.contour_scale > 0 and self.grid_cells > 1):
            raise ConfigError("mcd_scale, contour_scale must be > 0 and grid_cells > 1")
        if not 0.0 < self.reject_threshold < 1.0:
            raise ConfigError(f"reject_threshold must be in (0, 1), got {self.reject_threshold}")

    @property
    def weights(self) -> np.ndarray:
        """``(len(TERMS),)`` weights in :data:`TERMS` order."""
        return np.array([getattr(self, f"w_{t}") for t in TERMS], dtype=np.float64)

    @property
    def uses_mismatch(self) -> bool:
        return self.rule == "trapcc" or self.w_mismatch != 0.0


def map_scores(scores: np.ndarray, mapping: str) -> np.ndarray:
    """Detector scores -> probabilities in [0, 1] (``identity`` or ``sigmoid`` of logits)."""
    scores = np.asarray(scores, dtype=np.float64)
    if mapping == "identity":
        return scores
    if mapping == "sigmoid":
        return 1.0 / (1.0 + np.exp(-scores))
    raise ConfigError(f"unknown score_mapping {mapping!r}")


def _stack(clouds: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """All clouds in one array, with the instance index of each point."""
    sizes = np.array([len(c) for c in clouds], dtype=np.int64)
    points = np.concatenate(clouds).astype(np.float64) if sizes.sum() else np.zeros((0, 3))
    return points, np.repeat(np.arange(len(clouds)), sizes)


def _silhouettes(points: np.ndarray, owner: np.ndarray, n: int, view: tuple[int, int], config: FilterConfig):
    """``(n, cells, cells)`` occupancy of every instance's cloud in one 2D view."""
    cells, extent = config.grid_cells, config.grid_extent
    ij = np.clip(np.floor((points[:, list(view)] + extent) / (2 * extent) * cells).astype(np.int64), 0, cells - 1)
    flat = (owner * cells + ij[:, 0]) * cells + ij[:, 1]
    grid = np.zeros(n * cells * cells, dtype=bool)
    grid[flat] = True
    return grid.reshape(n, cells, cells)


def _dilate(grid: np.ndarray) -> np.ndarray:
    """3x3 dilation of a batch of ``(n, cells, cells)`` occupancy grids."""
    cells = grid.shape[1]
    padded = np.pad(grid, ((0, 0), (1, 1), (1, 1)))
    out = np.zeros_like(grid)
    for di in range(3):
        for dj in range(3):
            out |= padded[:, di : di + cells, dj : dj + cells]
    return out


def contour_differences(partials: list[np.ndarray], completions: list[np.ndarray], config: FilterConfig) -> np.ndarray:
    """Per instance, the mean over the side / front / top views of the share of the crop's
    occupied silhouette cells that the (dilated) completion silhouette misses. One pass for all."""
    n = len(partials)
    p_points, p_owner = _stack(partials)
    c_points, c_owner = _stack(completions)
    misses = np.zeros(n)
    for view in _VIEWS:
        theirs = _silhouettes(c_points, c_owner, n, view, config)
        covered = _dilate(theirs).reshape(-1)
        mine = _silhouettes(p_points, p_owner, n, view, config)
        occupied = np.flatnonzero(mine.reshape(-1))  # each occupied cell once
        owner = occupied // (config.grid_cells**2)
        missed = np.bincount(owner, weights=~covered[occupied], minlength=n)
        total = np.bincount(owner, minlength=n)
        misses += np.divide(missed, total, out=np.zeros(n), where=total > 0)
    return misses / len(_VIEWS)


def mcd(partials: list[np.ndarray], completions: list[np.ndarray]) -> np.ndarray:
    """TraPCC's MCD (Eq. 2) per instance: the mean *squared* distance from each crop point to
    its nearest completed point, canonical units. Pairs with an empty side get ``inf``."""
    out = np.full(len(partials), np.inf)
    ok = [k for k, (p, c) in enumerate(zip(partials, completions)) if len(p) and len(c)]
    if ok:
        distances = nearest_distances_batch([partials[k] for k in ok], [completions[k] for k in ok])
        out[ok] = [float(np.mean(d**2)) for d in distances]
    return out


def mismatch_terms(partial: np.ndarray, completion: np.ndarray, config: FilterConfig) -> tuple[float, float]:
    """(MCD, contour difference) of one canonical crop and its canonical completion (diagnostics)."""
    return float(mcd([partial], [completion])[0]), float(contour_differences([partial], [completion], config)[0])


def mismatch_scores(
    partials: list[np.ndarray], completions: list[np.ndarray], config: FilterConfig
) -> np.ndarray:
    """Mismatch score in [0, 1] for each (crop, completion) pair, both canonical (batched)."""
    if not partials:
        return np.zeros(0)
    terms = mcd(partials, completions) / config.mcd_scale  # inf where a side is empty: score 1
    terms += contour_differences(partials, completions, config) / config.contour_scale
    return 1.0 - np.exp(-terms)


def reject_mask(mismatch: np.ndarray, detection_scores: np.ndarray, config: FilterConfig) -> np.ndarray:
    """True where a detection is rejected: shape mismatch high AND detection score low.

    A detection with no mismatch score (NaN: too few points to judge) is kept — absence
    of evidence is not a reason to drop a detection.
    """
    probability = map_scores(detection_scores, config.score_mapping)
    mismatch = np.asarray(mismatch, dtype=np.float64)
    judged = np.isfinite(mismatch)
    return judged & (np.where(judged, mismatch, 0.0) > config.match_threshold) & (
        probability < config.detection_threshold
    )


# ============================================================================ physics evidence

#: The evidence terms, in the order of the logistic weights (:attr:`FilterConfig.weights`).
TERMS = ("density", "free_space", "ground_gap", "score", "mismatch")


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
#: BEV hash cell (metres) of the ground query: its boxes are 6 m wider than the cars, and the
#: default cell (a quarter of the median box width) would make most candidates false.
_GROUND_CELL = 1.0
#: Most beam columns sampled per box for the expected return count.
EXPECTED_COLUMNS = 64
#: Bins of the ray index: 0.2 deg of azimuth times 16 bands of elevation spanning the boxes'
#: elevation windows, plus one band below and one above them (rays no box can meet); the
#: product stays below 2^15 so the bin key is an int16 (numpy's radix sort).
_AZ_BINS = 1800
_EL_BANDS = 16
#: The ray index works on the points of the boxes' azimuth sectors only when these cover less
#: than this share of the circle (beyond it, selecting the subset costs more than it saves).
_SUBSET_SHARE = 0.75


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
    """Per-box values of the ray geometry, computed once per frame and gathered per pair
    (every value is the one a per-pair computation would give: same operands, same order)."""

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


def _slab(direction: tuple, lo: np.ndarray, hi: np.ndarray, index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Entry and exit parameters of the rays ``origin + t * direction`` (``direction``: three
    columns) through the boxes ``index`` whose bounds relative to the ray origin are ``lo``,
    ``hi`` (``(B, 3)``), axis by axis on columns."""
    tmin = tmax = None
    with np.errstate(divide="ignore", invalid="ignore"):
        for axis in range(3):
            inv = 1.0 / direction[axis]
            t1 = np.take(lo[:, axis], index) * inv
            t2 = np.take(hi[:, axis], index) * inv
            near, far = np.minimum(t1, t2), np.maximum(t1, t2)
            # fmax / fmin skip the NaN of a ray parallel to a slab starting on its plane
            tmin = near if tmin is None else np.fmax(tmin, near)
            tmax = far if tmax is None else np.fmin(tmax, far)
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


#: Slack (radians) of the elevation prefilter of :func:`_rays_towards`: it runs in the scan's
#: precision (float32 for sensor data) and must stay a superset of the rays that reach a box
#: (the exact box test comes after); a few float32 ulps of an angle.
_ELEVATION_SLACK = 1e-5


def _rays_towards(x, y, z, az_lo, az_hi, el_lo, el_hi, judged) -> tuple[np.ndarray, np.ndarray]:
    """(point, box) pairs whose ray from the sensor lies in the box's angular window (a
    superset of the rays that cross the box; :func:`evidence` tests them exactly).

    One pass over the scan in its own precision gives every point's azimuth bin; only the
    points in a bin some box needs (its azimuth sector, widened by one bin each way) go on:
    their elevation, a radix sort into (azimuth, elevation band) bins; each box's azimuth bins
    expand into the contiguous run of its elevation bands without a Python loop, and the
    elevation window is tested on the pairs by a gather of the points' elevations. Bins are
    widened by one on every side (float32 rounding at a bin edge loses no ray). The subset
    keeps scan order, so the pairs (and their order) are those of the whole scan sorted.
    Non-finite points never pair."""
    boxes_idx = np.flatnonzero(judged)
    if not len(boxes_idx):
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    lo_el = el_lo[boxes_idx] - _ELEVATION_SLACK
    hi_el = el_hi[boxes_idx] + _ELEVATION_SLACK
    e0 = float(lo_el.min())
    width = max(float(hi_el.max()) - e0, 1e-6) / _EL_BANDS
    b0 = np.floor((az_lo[boxes_idx] + np.pi) * (_AZ_BINS / (2 * np.pi))).astype(np.int64) - 1
    b1 = np.floor((az_hi[boxes_idx] + np.pi) * (_AZ_BINS / (2 * np.pi))).astype(np.int64) + 1
    nbins = np.minimum(b1 - b0 + 1, _AZ_BINS)
    box_of_bin = np.repeat(np.arange(len(boxes_idx)), nbins)
    local = np.arange(nbins.sum()) - np.repeat(np.cumsum(nbins) - nbins, nbins)
    az_bin = (np.repeat(b0, nbins) + local) % _AZ_BINS
    with np.errstate(invalid="ignore"):
        az = np.arctan2(y, x)
        scaled = (az + np.float32(np.pi)) * np.float32(_AZ_BINS / (2 * np.pi))
        key = np.where(np.isfinite(scaled), scaled, 0).astype(np.int16)
        np.clip(key, 0, _AZ_BINS - 1, out=key)
    # The boxes' azimuth sectors: the points outside them cannot pair (a cheap table lookup
    # instead of elevation, sort and counts over the whole scan, unless the sectors cover
    # most of the circle).
    wanted = np.zeros(_AZ_BINS, dtype=bool)
    wanted[az_bin] = True
    subset = None
    if np.count_nonzero(wanted) < _SUBSET_SHARE * _AZ_BINS:
        subset = np.flatnonzero(np.take(wanted, key))
        key, x, y, z = (np.take(a, subset) for a in (key, x, y, z))
    with np.errstate(invalid="ignore"):
        elevation = np.arctan2(z, np.sqrt(x * x + y * y))
        band = (elevation - elevation.dtype.type(e0)) * elevation.dtype.type(1.0 / width) + 1
        band = np.fmin(np.fmax(band, 0), _EL_BANDS + 1).astype(np.int16)  # NaN -> band 0: no box
    key *= np.int16(_EL_BANDS + 2)
    key += band
    n_bins = _AZ_BINS * (_EL_BANDS + 2)
    order = np.argsort(key, kind="stable")
    starts = np.zeros(n_bins + 1, dtype=np.int64)
    np.cumsum(np.bincount(key, minlength=n_bins), out=starts[1:])
    band_lo = np.clip(np.floor((lo_el - e0) / width).astype(np.int64), 1, _EL_BANDS)  # one band wider below
    band_hi = np.clip(np.floor((hi_el - e0) / width).astype(np.int64) + 2, 1, _EL_BANDS)  # and above
    bins = az_bin * (_EL_BANDS + 2)
    lo = starts[bins + np.take(band_lo, box_of_bin)]
    count = starts[bins + np.take(band_hi, box_of_bin) + 1] - lo
    pair_box = np.repeat(np.take(boxes_idx, box_of_bin), count)
    offset = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
    pair_point = np.take(order, np.repeat(lo, count) + offset)  # positions in the (sub)scan
    e = np.take(elevation, pair_point)
    dt = elevation.dtype
    with np.errstate(invalid="ignore"):
        keep = e >= np.take((el_lo - _ELEVATION_SLACK).astype(dt), pair_box)
        keep &= e <= np.take((el_hi + _ELEVATION_SLACK).astype(dt), pair_box)
    keep = np.flatnonzero(keep)
    pair_point = np.take(pair_point, keep)
    if subset is not None:
        pair_point = np.take(subset, pair_point)
    return pair_point, np.take(pair_box, keep)


def _expected_beams(boxes: Boxes, sensor: SensorModel, az_lo, az_hi, el_lo, el_hi, judged,
                    table: _BoxTable | None = None) -> np.ndarray:
    """Beams of the sensor model (rings x azimuth steps) whose rays hit each box."""
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
    # Trigonometry once per (box, column) and per ring; the beams gather it.
    column_box = np.repeat(np.arange(len(idx)), n_az)
    column = np.arange(n_az.sum()) - np.repeat(np.cumsum(n_az) - n_az, n_az)
    azimuth = az_lo[idx][column_box] + (column + 0.5) * step * stretch[column_box]
    cos_az, sin_az = np.cos(azimuth), np.sin(azimuth)
    cos_el, sin_el = np.cos(rings), np.sin(rings)
    per = n_az * n_ring
    beam_box = np.repeat(np.arange(len(idx)), per)  # position in idx
    local = np.arange(per.sum()) - np.repeat(np.cumsum(per) - per, per)
    n_az_b = np.take(n_az, beam_box)
    col = np.take(np.cumsum(n_az) - n_az, beam_box) + local % n_az_b
    ring = np.take(r_lo, beam_box) + local // n_az_b
    ce = np.take(cos_el, ring)
    box = np.take(idx, beam_box)
    direction = to_box_local(ce * np.take(cos_az, col), ce * np.take(sin_az, col), np.take(sin_el, ring),
                             0.0, 0.0, 0.0, np.take(table.cos, box), np.take(table.sin, box))
    tmin, tmax = _slab(direction, *table.body, box)
    hit = tmax >= np.maximum(tmin, 0.0)
    weight = np.zeros(len(boxes))
    weight[idx] = stretch
    out += np.bincount(box[hit], minlength=len(boxes)) * weight
    return out


def local_ground(points: np.ndarray, boxes: Boxes, reach: float = GROUND_REACH, quantile: float = 0.05) -> np.ndarray:
    """Ground height around each box: the ``quantile`` of the z of the returns within ``reach``
    metres of its footprint and from 3 m below to 1 m above its bottom (NaN when there are none)."""
    n = len(boxes)
    if n == 0:
        return np.zeros(0)
    bottom = boxes.center[:, 2] - boxes.size[:, 2] / 2
    centre = np.c_[boxes.center[:, :2], bottom - 1.0]
    wide = Boxes(centre, np.c_[boxes.size[:, :2] + 2 * reach, np.full(n, 4.0)], boxes.yaw)
    points = np.asarray(points)
    pair_point, pair_box = pairs_in_boxes(points, wide, cell=_GROUND_CELL)
    z = np.take(points[:, 2], pair_point)
    z = np.take(z, np.argsort(pair_box.astype(np.int16 if n < 32767 else np.int64), kind="stable"))  # by box
    ends = np.cumsum(np.bincount(pair_box, minlength=n)).tolist()
    out = np.full(n, np.nan)
    for b, (start, end) in enumerate(zip([0, *ends[:-1]], ends)):  # one partial sort per box (boxes, not points)
        if end > start:
            k = int(quantile * (end - start - 1))
            out[b] = np.partition(z[start:end], k)[k]
    return out


_SIDE_POOL: ThreadPoolExecutor | None = None


def _side_pool() -> ThreadPoolExecutor:
    global _SIDE_POOL
    if _SIDE_POOL is None:
        _SIDE_POOL = ThreadPoolExecutor(max_workers=1, thread_name_prefix="pcc-filter")
    return _SIDE_POOL


def evidence(points: np.ndarray, boxes: Boxes, sensor: SensorModel | None = None, workers: int = 1) -> Evidence:
    """Free-space, return-count and ground-contact measurements of every box, from the scan.

    The sensor sits at the scan frame's origin (true for a scan in its own sensor frame).
    Vectorised over (ray, box) pairs: one pass over the scan, no loop over points or boxes;
    the pairs' geometry runs column by column in float64 on per-box values gathered once.
    ``workers`` >= 2: the sensor model's expected returns and the local ground (a query of
    its own over the scan) are measured on a second thread while this one follows the rays
    (numpy releases the GIL in its loops); the values are the same either way.
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
    table = _BoxTable(boxes)

    def beams_and_ground() -> tuple[np.ndarray, np.ndarray]:
        return _expected_beams(boxes, sensor, az_lo, az_hi, el_lo, el_hi, judged, table), local_ground(points, boxes)

    side_job = _side_pool().submit(beams_and_ground) if workers > 1 else None
    # contiguous columns: numpy's SIMD loops (arctan2 among them) skip strided arrays
    x, y, z = (np.ascontiguousarray(points[:, k]) for k in range(3))
    pair_point, pair_box = _rays_towards(x, y, z, az_lo, az_hi, el_lo, el_hi, judged)
    # Box-frame ray: origin (the sensor, one per box) + t * (point - origin); t = 1 at the return.
    local = to_box_local(
        np.take(x, pair_point).astype(np.float64), np.take(y, pair_point).astype(np.float64),
        np.take(z, pair_point).astype(np.float64), np.take(boxes.center[:, 0], pair_box),
        np.take(boxes.center[:, 1], pair_box), np.take(boxes.center[:, 2], pair_box),
        np.take(table.cos, pair_box), np.take(table.sin, pair_box),
    )
    direction = tuple(local[a] - np.take(table.origin[:, a], pair_box) for a in range(3))
    tin, tout = _slab(direction, *table.body, pair_box)
    through = np.flatnonzero(tout >= np.maximum(tin, 0.0))  # rays that cross the box at all
    pair_box, tin, tout = np.take(pair_box, through), np.take(tin, through), np.take(tout, through)
    direction = tuple(np.take(d, through) for d in direction)
    cin, cout = _slab(direction, *table.core, pair_box)
    through_core = cout >= np.maximum(cin, 0.0)
    inside = (tin <= 1.0) & (1.0 <= tout)
    occluded = 1.0 < tin
    stop = through_core & (tin <= 1.0) & (1.0 <= cout)
    passed = through_core & (1.0 > cout)

    def count(mask):
        return np.bincount(pair_box[mask], minlength=n).astype(np.float64)

    n_in, n_occ, n_stop = count(inside), count(occluded), count(stop)
    n_pass, n_rays = count(passed), np.bincount(pair_box, minlength=n).astype(np.float64)
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


def score_logit(scores: np.ndarray, mapping: str) -> np.ndarray:
    """The detector score as a logit: raw for ``sigmoid`` (already a logit), ``logit(p)`` for
    probabilities (clipped to [1e-4, 1 - 1e-4])."""
    scores = np.asarray(scores, dtype=np.float64)
    if mapping == "sigmoid":
        return scores
    p = np.clip(map_scores(scores, mapping), 1e-4, 1 - 1e-4)
    return np.log(p / (1 - p))


def term_matrix(terms: dict[str, np.ndarray]) -> np.ndarray:
    """``(N, len(TERMS))`` feature matrix; a missing mismatch (NaN: not judged) reads 0."""
    n = len(next(iter(terms.values())))
    cols = [np.nan_to_num(np.asarray(terms.get(t, np.zeros(n)), dtype=np.float64), nan=0.0) for t in TERMS]
    return np.stack(cols, axis=1)


def false_probability(terms: dict[str, np.ndarray], config: FilterConfig) -> np.ndarray:
    """``sigmoid(w_bias + X @ w)``: the calibrated probability that each detection is false."""
    x = term_matrix(terms)
    z = config.w_bias + x @ config.weights
    return 1.0 / (1.0 + np.exp(-z))


def filter_terms(
    points: np.ndarray, boxes: Boxes, config: FilterConfig, mismatch: np.ndarray | None = None, workers: int = 1
) -> dict[str, np.ndarray]:
    """Every term of the evidence rule for ``boxes`` in ``points`` (plus the raw counts);
    ``workers``: CPU threads measuring them (:func:`evidence`)."""
    ev = evidence(points, boxes, SENSOR_PRESETS[config.sensor], workers=workers)
    out = ev.as_dict()
    out["score"] = score_logit(boxes.score, config.score_mapping)
    out["mismatch"] = np.full(len(boxes), np.nan) if mismatch is None else np.asarray(mismatch, dtype=np.float64)
    return out


# ============================================================================ visible decisions

#: class_id of the extra hypothesis carrying the filter's probability that a detection is false.
SCORE_CLASS_ID = "pcc_filter_score"
#: class_id prefix of the hypotheses carrying the terms behind it (``pcc_filter/density`` ...).
TERM_CLASS_PREFIX = "pcc_filter/"


def decision_texts(result) -> list[str] | None:
    """RViz text per detection: ``"Car 8.30 | p_false 0.02 kept"`` (evidence rule) or
    ``"Car 0.40 | mismatch 0.71 rejected"`` (trapcc rule); None when nothing was judged."""
    n = len(result.detections)
    if not n:
        return None
    score = result.filter_score if result.filter_score is not None else np.full(n, np.nan)
    out = []
    for i in range(n):  # one label per box
        head = f"{result.detections.label[i]} {result.detections.score[i]:.2f}"
        if np.isfinite(score[i]):
            out.append(f"{head} | p_false {score[i]:.2f} {result.status[i]}")
        elif np.isfinite(result.mismatch[i]):
            out.append(f"{head} | mismatch {result.mismatch[i]:.2f} {result.status[i]}")
        else:
            out.append(f"{head} | {result.status[i]}")
    return out


def annotate_detections(detections: list, result, index: np.ndarray, classes=None) -> list:
    """Copies of ``detections`` (``vision_msgs/Detection3D``, detection ``index[k]`` of
    ``result``) with the filter's decision appended to ``results``: one
    ``ObjectHypothesisWithPose`` ``class_id="pcc_filter_score"``, score = probability that the
    detection is false, then one ``pcc_filter/<term>`` per finite term (score = the term's
    value), all with the box pose. The detector's own hypotheses come first, untouched."""
    if result.filter_score is None and not np.isfinite(result.mismatch).any():
        return list(detections)
    out = []
    for det, i in zip(detections, index):  # a few dozen detections per frame
        values: list[tuple[str, float]] = []
        score = np.nan if result.filter_score is None else result.filter_score[i]
        if np.isfinite(score):
            values.append((SCORE_CLASS_ID, float(score)))
        for term in TERMS:
            v = result.filter_terms.get(term)
            if v is not None and np.isfinite(v[i]):
                values.append((TERM_CLASS_PREFIX + term, float(v[i])))
        if np.isfinite(result.mismatch[i]) and not any(k.endswith("/mismatch") for k, _ in values):
            values.append((TERM_CLASS_PREFIX + "mismatch", float(result.mismatch[i])))
        extra = [
            new_message(
                "vision_msgs/msg/ObjectHypothesisWithPose",
                classes,
                hypothesis=new_message("vision_msgs/msg/ObjectHypothesis", classes, class_id=k, score=v),
                pose=new_message(
                    "geometry_msgs/msg/PoseWithCovariance", classes, pose=det.bbox.center,
                    covariance=np.zeros(36, dtype=np.float64),
                ),
            )
            for k, v in values
        ]
        out.append(
            new_message(
                "vision_msgs/msg/Detection3D", classes, header=det.header, results=[*det.results, *extra],
                bbox=det.bbox, id=det.id,
            )
        )
    return out


def decision_counts(status: np.ndarray) -> dict[str, int]:
    """kept / rejected / skipped counts of one frame's statuses (for /diagnostics)."""
    status = np.asarray(status, dtype=object)
    return {k: int((status == k).sum()) for k in ("kept", "rejected", "skipped")}
