"""The filter's beam model from the data: ``sensor: auto`` estimates the LiDAR's elevation
table and azimuth step from the scans instead of assuming a preset (docs/filter.md, "Beam
model").

* **With a ring field** (Velodyne, Ouster and Hesai drivers publish one; nuScenes scans carry
  ring 0..31): each ring's elevation is the median of its returns' elevations (robust to
  multi-path, motion and the lasers' small offsets from the sensor origin).
* **Without one**: beams are the peaks of the histogram of the returns' elevations
  ``asin(z / r)`` (a beam's returns share one elevation whatever their range, so each beam is a
  spike); returns nearer than :data:`MIN_RANGE` (the ego body; near range magnifies the lasers'
  offsets from the origin) are left out, and a peak must stand out from the valley to its
  neighbour (:data:`VALLEY`), so clutter between beams does not make beams.
* **Azimuth step**: the mean gap between consecutive returns of one beam in azimuth, the gaps
  of a beam's missing returns (over :data:`GAP_FACTOR` times the median gap) left out. Two
  units firing along the same elevations, or two lasers merged into one histogram peak, give
  half the gap: the product beams x columns (what the expected returns count) stays right.

:class:`BeamModel` keeps one estimate per node (the first frame with beam structure), re-checks
it every :data:`RECHECK_FRAMES` frames and re-adopts (logged) when it drifted; until the first
estimate succeeds it falls back to the ``hdl64`` preset (logged once).
"""

from __future__ import annotations

import logging

import numpy as np

from pcc_ros.errors import ConfigError
from pcc_ros.geometry.beams import SENSOR_PRESETS, SensorModel, sensor_preset
from pcc_ros.lograte import worth_logging

log = logging.getLogger(__name__)

#: ``sensor`` value that estimates the beam model from the scans.
AUTO = "auto"
#: Metres: nearer returns are left out of the estimate. A beam whose returns all lie nearer
#: hits the ground before it reaches any box beyond this range, so its absence from the table
#: changes no expected count there; and near range magnifies the lasers' offsets from the origin.
MIN_RANGE = 5.0
#: The ring path's nearer bound (a ring's median is robust to the offsets; the lowest beams of
#: a high-mounted sensor return only within a few metres).
RING_MIN_RANGE = 2.5
#: Returns (beyond MIN_RANGE) a frame needs for an estimate.
MIN_POINTS = 2000
#: Returns a beam (ring or histogram peak) needs to count.
MIN_BEAM_POINTS = 8
#: Histogram bin of the ring-less estimate, degrees; peaks closer than PEAK_WINDOW are one beam
#: (the densest preset, Pandar64, steps 1/6 deg).
BIN_DEG = 0.01
PEAK_WINDOW_DEG = 0.07
#: A peak survives when the histogram between it and a higher neighbour falls below this share
#: of its height (a real beam gap); else the two are one beam.
VALLEY = 0.5
#: Ring-less estimate: lasers sit a few centimetres above or below the scan frame's origin
#: (the HDL-64E's two blocks ~0.1 and ~0.2 m), which smears a beam's elevation seen from the
#: origin with range. Per band of BAND_DEG of elevation, the vertical offset (within
#: +-OFFSET_MAX m, steps of OFFSET_STEP) that makes the histogram sharpest is taken out first.
BAND_DEG = 4.0
OFFSET_MAX = 0.3
OFFSET_STEP = 0.02
#: Returns of one band the offset search looks at, at most (an even subsample).
OFFSET_SAMPLE = 2000
#: A band whose returns light at least this share of the columns, and holding more than
#: SPLIT_FACTOR times as many peaks as returns per lit column, has its beams counted from the
#: returns instead (:func:`_split_checked`).
LIT_SHARE = 0.5
SPLIT_FACTOR = 1.25
#: Share of the returns that must lie within a beam's spike for the scan to have beam structure.
MIN_STRUCTURE = 0.5
#: Gaps in azimuth over this many times the median gap are missing returns, not the step.
GAP_FACTOR = 1.5
#: Frames between two checks of an adopted estimate; frames between retries while none succeeded.
RECHECK_FRAMES = 100
RETRY_FRAMES = 10
#: An estimate differs from the adopted one (drift) when the beam count differs, an elevation
#: moved more than this many degrees or the azimuth step more than this share.
DRIFT_DEG = 0.1
DRIFT_STEP = 0.1
#: The model used until a first estimate succeeds.
FALLBACK = "hdl64"

#: The ground under the sensor is read from the lowest return of each BEV cell (GROUND_CELL
#: metres; objects standing on the ground leave it visible around them) beyond GROUND_FROM metres
#: (past the ego vehicle's body), the GROUND_CELLS cells nearest the vehicle: the road near it,
#: before a slope or the sensor's pitch moves it (the real nuScenes frame's ground rises 0.35 m
#: from 4 to 20 m), and beyond the few cells a near car's body fills.
GROUND_FROM, GROUND_CELL, GROUND_CELLS = 3.0, 1.0, 100
#: Height bins of the ground histogram (metres).
GROUND_BIN = 0.05
#: Plausible mounting heights (metres above the ground): a small robot to a truck's roof.
MOUNT_RANGE = (0.2, 4.5)
#: The sensor's height above the ground the presets' ``sensor_thresholds`` were set at (SynthCars
#: simulates every preset this high, as KITTI's car carries its HDL-64E), and how far a sensor's
#: own height may lie from it before the filter warns that a preset's threshold does not hold
#: for it (a VLP-16 0.8 or 2.4 m high lost 2.5-4.1 % of a street's cars at the vlp16 entry;
#: docs/filter.md): such a mount needs its own threshold (``pcc calibrate-filter --sensor-from``).
CALIBRATION_HEIGHT = 1.73
HEIGHT_TOLERANCE = 0.4


def _angles(points: np.ndarray, min_range: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Elevation and azimuth (degrees) of the finite returns beyond ``min_range``, which they
    are, and their x, y, z (float64)."""
    xyz = np.asarray(points, dtype=np.float64)[:, :3]
    r = np.sqrt(np.einsum("ij,ij->i", xyz, xyz))
    with np.errstate(invalid="ignore"):
        use = np.flatnonzero(np.isfinite(r) & (r > min_range))
    xyz = xyz[use]
    el = _elevation(xyz, 0.0)
    az = np.degrees(np.arctan2(xyz[:, 1], xyz[:, 0]))
    return el, az, use, xyz


def _elevation(xyz: np.ndarray, offset: float) -> np.ndarray:
    """Elevation (degrees) of points seen from ``offset`` metres above the origin."""
    z = xyz[:, 2] - offset
    r = np.sqrt(xyz[:, 0] ** 2 + xyz[:, 1] ** 2 + z**2)
    return np.degrees(np.arcsin(np.clip(z / np.maximum(r, 1e-9), -1.0, 1.0)))


def _offset_corrected(el: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    """Elevations with each BAND_DEG band's best vertical laser offset taken out (module doc);
    a band keeps offset 0 unless another is sharper (exact data stays exact). The sharpness of
    an offset is the concentration of the band's elevations in BIN_DEG bins (sum of squared
    counts), all offsets of a band in one histogram."""
    out = el.copy()
    band = np.floor(el / BAND_DEG).astype(np.int64)
    offsets = np.r_[0.0, np.arange(-OFFSET_MAX, OFFSET_MAX + OFFSET_STEP / 2, OFFSET_STEP)]
    order = np.argsort(band, kind="stable")
    edges = np.flatnonzero(np.diff(band[order])) + 1
    for mine in np.split(order, edges):  # a dozen bands
        if len(mine) < 4 * MIN_BEAM_POINTS:
            continue
        sample = xyz[mine[:: max(1, len(mine) // OFFSET_SAMPLE)]]
        z = sample[:, 2][None, :] - offsets[:, None]  # (offsets, points)
        d2 = sample[:, 0] ** 2 + sample[:, 1] ** 2
        e = np.degrees(np.arctan2(z, np.sqrt(d2)[None, :]))
        cells = np.floor((e - e.min()) / BIN_DEG).astype(np.int64)
        width = int(cells.max()) + 1
        counts = np.bincount((cells + np.arange(len(offsets))[:, None] * width).ravel(),
                             minlength=len(offsets) * width).reshape(len(offsets), width).astype(np.float64)
        sharpness = np.einsum("ij,ij->i", counts, counts)
        best = int(np.argmax(sharpness))  # the first maximum: offset 0 on ties
        if best:
            out[mine] = _elevation(xyz[mine], float(offsets[best]))
    return out


def _group_medians(values: np.ndarray, group: np.ndarray, n_groups: int) -> tuple[np.ndarray, np.ndarray]:
    """Per group: the (lower) median of ``values`` (degrees, within +-90) and the count (one
    sort of group x 1000 + value, no loop)."""
    order = np.argsort(group * 1000.0 + values)
    counts = np.bincount(group, minlength=n_groups)
    starts = np.cumsum(counts) - counts
    mid = starts + np.maximum(counts - 1, 0) // 2
    medians = np.full(n_groups, np.nan)
    has = counts > 0
    medians[has] = values[order[mid[has]]]
    return medians, counts


def _ring_table(el: np.ndarray, rings: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Per-ring median elevations (ascending) and each return's beam index in that table."""
    ring = np.asarray(rings, dtype=np.float64)
    ok = np.isfinite(ring) & (ring >= 0) & (ring < 65536)
    if not ok.any():
        return None
    ring_id = ring[ok].astype(np.int64)
    medians, counts = _group_medians(el[ok], ring_id, int(ring_id.max()) + 1)
    beams = np.flatnonzero(counts >= MIN_BEAM_POINTS)
    if len(beams) < 2:
        return None
    order = np.argsort(medians[beams], kind="stable")
    rank = np.full(len(counts), -1)
    rank[beams[order]] = np.arange(len(beams))
    beam = np.full(len(el), -1)
    beam[ok] = rank[ring_id]
    return medians[beams[order]], beam


def _histogram_peaks(el: np.ndarray) -> np.ndarray:
    """Centres (degrees, ascending) of the beams' spikes in the elevation histogram."""
    lo = np.floor(el.min() / BIN_DEG) - 2
    idx = (np.floor(el / BIN_DEG) - lo).astype(np.int64)
    hist = np.bincount(idx).astype(np.float64)
    hist = np.convolve(hist, [0.25, 0.5, 0.25], mode="same")  # a spike split over two bins stays one peak
    w = max(1, round(PEAK_WINDOW_DEG / BIN_DEG))
    padded = np.pad(hist, w)
    windows = np.lib.stride_tricks.sliding_window_view(padded, 2 * w + 1)
    local_max = (hist >= windows.max(axis=1)) & (hist > 0)
    # a plateau gives several equal maxima: keep the first of each run
    cand = np.flatnonzero(local_max & ~np.r_[False, local_max[:-1]])
    cand = cand[hist[cand] >= MIN_BEAM_POINTS / 4]
    # Merge a peak into its higher neighbour unless the histogram dips between them
    # (a loop over the peaks, at most a few hundred).
    keep = list(cand)
    changed = True
    while changed and len(keep) > 1:
        changed = False
        for k in range(len(keep) - 1):
            a, b = keep[k], keep[k + 1]
            valley = hist[a : b + 1].min()
            if valley > VALLEY * min(hist[a], hist[b]):
                del keep[k if hist[a] < hist[b] else k + 1]
                changed = True
                break
    return (np.asarray(keep, dtype=np.float64) + lo + 0.5) * BIN_DEG


def _peak_table(el: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Ring-less table: histogram peaks refined to the median of the returns near each, and
    each return's beam (-1: between beams); None when the scan shows no beam structure."""
    peaks = _histogram_peaks(el)
    if len(peaks) < 2:
        return None
    mids = (peaks[1:] + peaks[:-1]) / 2
    nearest = np.searchsorted(mids, el)
    gap = np.minimum(np.diff(np.r_[-np.inf, peaks]), np.diff(np.r_[peaks, np.inf]))
    tol = np.minimum(0.3 * gap, 0.1)
    near = np.abs(el - peaks[nearest]) <= tol[nearest]
    medians, counts = _group_medians(el[near], nearest[near], len(peaks))
    beams = np.flatnonzero(counts >= MIN_BEAM_POINTS)
    if len(beams) < 2 or counts[beams].sum() < MIN_STRUCTURE * len(el):
        return None
    rank = np.full(len(peaks), -1)
    rank[beams] = np.arange(len(beams))
    return medians[beams], np.where(near, rank[nearest], -1)


def _split_checked(elevations: np.ndarray, el: np.ndarray, az: np.ndarray, step: float) -> np.ndarray:
    """The peak table with each lit band's beam count checked against the returns per firing.

    A laser fires once per column, so a band of elevation its beams light all round (the
    ground) holds about (its beams) returns per column that has any. Where the histogram
    found clearly more peaks in such a band (a real laser's offsets from the origin smear its
    elevation with range into several spikes), the band's beams are that count instead, at
    equal-share quantiles of its returns. Exact data never has more peaks than returns per
    column, so its table is left as found."""
    columns = max(1, round(360.0 / step))
    band = np.floor(el / BAND_DEG).astype(np.int64)
    column = np.floor((az + 180.0) / step).astype(np.int64) % columns
    keep = np.ones(len(elevations), dtype=bool)
    extra: list[np.ndarray] = []
    table_band = np.floor(elevations / BAND_DEG).astype(np.int64)
    for value in np.unique(table_band):  # a dozen bands
        mine = band == value
        lit = np.count_nonzero(np.bincount(column[mine], minlength=columns))
        if lit < LIT_SHARE * columns:
            continue
        per_column = mine.sum() / lit
        found = int((table_band == value).sum())
        if found > SPLIT_FACTOR * per_column + 0.5:
            beams = max(1, round(per_column))
            keep &= table_band != value
            extra.append(np.quantile(el[mine], (np.arange(beams) + 0.5) / beams))
    return np.sort(np.concatenate([elevations[keep], *extra]))


def _azimuth_step(az: np.ndarray, beam: np.ndarray) -> float | None:
    """Mean gap in azimuth between consecutive returns of one beam (missing returns' gaps left out)."""
    mine = beam >= 0
    a, b = az[mine], beam[mine]
    order = np.argsort(b * 1000.0 + a)  # by beam, then azimuth (degrees within +-180)
    a, b = a[order], b[order]
    d = np.diff(a)[np.diff(b) == 0]
    positive = d[d > 1e-4]
    if len(positive) < 100:
        return None
    d = d[d < GAP_FACTOR * np.median(positive)]
    return float(d.mean())


def estimate_sensor(points: np.ndarray, rings: np.ndarray | None = None, min_range: float = MIN_RANGE,
                    name: str = "estimated") -> SensorModel | None:
    """The beam model of one scan (``(N, >=3)`` in the sensor frame), or None when it shows no
    beam structure (too few returns, no spikes in elevation): see the module docstring.
    ``rings``: the scan's ring field, one value per point (NaN / negative: unknown)."""
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] < 3:
        raise ValueError(f"points must be (N, >=3), got shape {points.shape}")
    table = None
    if rings is not None:
        rings = np.asarray(rings).reshape(-1)
        if len(rings) != len(points):
            raise ValueError(f"{len(rings)} ring values for {len(points)} points")
        el, az, use, _ = _angles(points, min(min_range, RING_MIN_RANGE))
        if len(el) >= MIN_POINTS:
            table = _ring_table(el, rings[use])
    ringless = table is None
    if ringless:
        el, az, use, xyz = _angles(points, min_range)
        if len(el) < MIN_POINTS:
            return None
        el = _offset_corrected(el, xyz)
        table = _peak_table(el)
    if table is None:
        return None
    elevations, beam = table
    step = _azimuth_step(az, beam)
    if step is None or not 0.0 < step <= 45.0:
        return None
    if ringless:
        elevations = _split_checked(elevations, el, az, step)
    return SensorModel(tuple(elevations), step, name)


def same_layout(a: SensorModel, b: SensorModel, tol_deg: float = DRIFT_DEG, step_tol: float = DRIFT_STEP,
                missing: float = 0.0) -> bool:
    """Whether two beam models agree (no drift): same beam count, elevations within ``tol_deg``
    and azimuth steps within ``step_tol`` of each other. ``missing`` > 0: ``a`` may lack up to that
    share of ``b``'s beams, or have that share more (a ring-less estimate misses the beams that
    return nothing beyond :data:`MIN_RANGE`, and a real laser's offsets may split one), each of
    ``a``'s beams within ``tol_deg`` of one of ``b``'s."""
    step = abs(a.azimuth_resolution_deg - b.azimuth_resolution_deg) / b.azimuth_resolution_deg
    if missing <= 0.0:
        if a.rings != b.rings:
            return False
        el = np.abs(np.subtract(a.elevations_deg, b.elevations_deg)).max()
    else:
        if abs(a.rings - b.rings) > missing * b.rings:  # a split beam may also count twice
            return False
        el = np.abs(np.subtract.outer(a.elevations_deg, b.elevations_deg)).min(axis=1).max()
    return bool(el <= tol_deg and step <= step_tol)


#: Matching an estimate to a named preset (:func:`matching_preset`): elevations within this many
#: degrees. Wider than :data:`DRIFT_DEG`: a real unit's own calibration departs from its datasheet
#: (the nuScenes HDL-32E read with its ring field: up to 0.32 deg), while presets of one beam count
#: differ by a degree or more (``test/test_sensor_thresholds.py`` checks the table).
MATCH_DEG = 0.5
#: ... and azimuth steps within this share.
MATCH_STEP = DRIFT_STEP
#: ... and a ring-less estimate may lack this share of the beams the preset has over its span: a
#: beam needs MIN_BEAM_POINTS returns beyond MIN_RANGE, which an upward beam under open sky or
#: the lowest one at the span's edge may not get, and two beams 1/3 deg apart may merge into one
#: histogram peak (SynthCars: OS1-128 up to 4 of 123, VLP-32C 4 of 31 on 1 frame of 32; the real
#: KITTI HDL-64E scan, its two blocks merged and split by the laser offsets: 59 beams for 63).
MATCH_MISSING = 0.15
#: ... and a ring-less estimate's beams may lie this many degrees from the preset's: without the
#: ring field each beam is a histogram peak of the returns' elevations, which the lasers' offsets
#: from the origin smear and skew (the real nuScenes HDL-32E scan read without its ring field: up to
#: 0.61 deg from the datasheet, its ring medians within 0.32 deg). Random ring-less views of every
#: preset (beams dropped, each moved up to 0.45 deg, the step 5 % off) match no wrong preset at
#: this tolerance (``test/test_sensor_thresholds.py``): the beam count and the step still decide.
MATCH_DEG_RINGLESS = 0.7


def ringless_view(preset: SensorModel, low: float, high: float) -> SensorModel | None:
    """What the ring-less estimate can see of ``preset`` between ``low`` and ``high`` degrees: its
    beams there, those closer than :data:`PEAK_WINDOW_DEG` merged into one (two stacked units
    firing along one elevation are one histogram spike), and the azimuth step divided by the beams
    per merged elevation (the estimate reads two units' returns along one elevation as one beam at
    half the step). None when fewer than 2 beams lie there. A scan shows no beam whose returns
    all lie within :data:`MIN_RANGE` (the steep downward ones) and none that hits nothing (the
    upward ones under open sky), so the estimate is compared with the preset over its own span."""
    el = np.asarray(preset.elevations_deg)
    el = el[(el >= low) & (el <= high)]
    if len(el) < 2:
        return None
    starts = np.r_[True, np.diff(el) >= PEAK_WINDOW_DEG]
    merged = np.add.reduceat(el, np.flatnonzero(starts)) / np.diff(np.r_[np.flatnonzero(starts), len(el)])
    if len(merged) < 2:
        return None
    step = preset.azimuth_resolution_deg * len(merged) / len(el)
    return SensorModel(tuple(merged), step, preset.name)


def matching_preset(model: SensorModel, presets: dict[str, SensorModel] | None = None,
                    tol_deg: float = MATCH_DEG, step_tol: float = MATCH_STEP) -> str | None:
    """The name of the preset ``model`` is (:func:`same_layout` within ``tol_deg`` / ``step_tol``),
    whole (a ring-field estimate: every beam) or as a ring-less estimate sees it over the model's
    span (:func:`ringless_view`, each beam within :data:`MATCH_DEG_RINGLESS`); the nearest in
    elevation when several match; None when none does
    (an unknown sensor). A preset's own model matches itself."""
    presets = SENSOR_PRESETS if presets is None else presets
    low, high = model.elevations_deg[0] - tol_deg, model.elevations_deg[-1] + tol_deg
    ringless_tol = max(tol_deg, MATCH_DEG_RINGLESS)
    best, best_err = None, np.inf
    for name, preset in presets.items():
        views = ((preset, 0.0, tol_deg), (ringless_view(preset, low, high), MATCH_MISSING, ringless_tol))
        for view, missing, tol in views:
            if view is None or not same_layout(model, view, tol, step_tol, missing):
                continue
            err = float(np.abs(np.subtract.outer(model.elevations_deg, view.elevations_deg)).min(axis=1).mean())
            if err < best_err:
                best, best_err = name, err
    return best


class BeamModel:
    """The sensor model the filter assumes, frame after frame: a named preset, or (``auto``)
    the estimate of :func:`estimate_sensor`, made on the first frame with beam structure, kept,
    and re-checked every ``recheck_every`` frames (re-adopted and logged when it drifted).
    Before the first estimate: the :data:`FALLBACK` preset (logged once)."""

    def __init__(self, name: str = AUTO, recheck_every: int = RECHECK_FRAMES, retry_every: int = RETRY_FRAMES) -> None:
        if name != AUTO and name not in SENSOR_PRESETS:
            raise ConfigError(f"sensor must be {AUTO!r} or one of {sorted(SENSOR_PRESETS)}, got {name!r}")
        self.name = name
        self.recheck_every, self.retry_every = max(1, recheck_every), max(1, retry_every)
        self.model: SensorModel | None = None if name == AUTO else sensor_preset(name)
        #: the preset the model is (a named one: itself; auto: :func:`matching_preset` of the
        #: adopted estimate, None before it or for an unknown sensor): what per-sensor settings key on
        self.preset: str | None = None if name == AUTO else name
        self.frames = 0  # frames seen
        self._next = 0  # frame index of the next estimate
        self.estimates = 0  # estimates made (successful or not)
        self.drifts = 0  # re-adoptions after a drift
        #: the sensor's height above the ground (auto: read at each estimate, the last one seen;
        #: None: a named preset, or no ground seen yet)
        self.mount_height: float | None = None
        self._warned_fallback = False
        self._failures = 0  # estimates in a row that found no beam structure before the first success

    @property
    def auto(self) -> bool:
        return self.name == AUTO

    def due(self) -> bool:
        """Whether the next frame is estimated (callers read the ring field only then)."""
        return self.auto and self.frames >= self._next

    def for_frame(self, points: np.ndarray, rings: np.ndarray | None = None) -> SensorModel:
        """The model for this frame (estimating from it when due)."""
        if self.due():
            self._estimate(points, rings)
        self.frames += 1
        if self.model is None:
            if not self._warned_fallback:
                self._warned_fallback = True
                log.warning("sensor auto: no beam structure in the first frame (%d points); the filter assumes the "
                            "%s beam model until an estimate succeeds (retried after %d frames, then less often). A "
                            "scanner without beam rings (solid-state, non-repetitive) never shows one: set sensor to "
                            "the preset nearest its returns per degree (docs/filter.md)", len(points), FALLBACK,
                            self.retry_every)
            return SENSOR_PRESETS[FALLBACK]
        return self.model

    def off_height(self) -> bool:
        """Whether the sensor sits farther than :data:`HEIGHT_TOLERANCE` from the
        :data:`CALIBRATION_HEIGHT` the presets' thresholds were set at (unknown height: no)."""
        return self.mount_height is not None and abs(self.mount_height - CALIBRATION_HEIGHT) > HEIGHT_TOLERANCE

    def _estimate(self, points: np.ndarray, rings: np.ndarray | None) -> None:
        self.estimates += 1
        if len(points):
            height = ground_height(points)
            if height is not None:
                self.mount_height = height
        found = estimate_sensor(points, rings) if len(points) else None
        if found is None:
            # Before a first success, retries back off (retry_every, twice that, ... up to recheck_every):
            # a scanner without rings (solid-state, non-repetitive) never shows beams, and each try costs
            # an estimate's tens of milliseconds.
            self._failures += 1
            wait = min(self.retry_every * 2 ** (self._failures - 1), self.recheck_every)
            self._next = self.frames + (wait if self.model is None else self.recheck_every)
            return
        self._next = self.frames + self.recheck_every
        if self.model is None:
            self.model, self.preset = found, matching_preset(found)
            log.info("sensor auto: %s (from frame %d%s); %s; %s", found.describe(), self.frames,
                     ", ring field" if rings is not None else "", self._preset_text(),
                     "ground not seen" if self.mount_height is None else f"{self.mount_height:.2f} m above the ground")
        elif not same_layout(found, self.model):
            self.drifts += 1
            was, self.model, self.preset = self.model, found, matching_preset(found)
            if worth_logging(self.drifts):
                log.warning("sensor auto: the beam model drifted at frame %d: was %s, now %s; re-adopted (%d such "
                            "re-adoptions); %s", self.frames, was.describe(), found.describe(), self.drifts,
                            self._preset_text())

    def _preset_text(self) -> str:
        return f"matches the {self.preset} preset" if self.preset else "matches no preset"


def ground_height(points: np.ndarray) -> float | None:
    """The ground's height below the sensor (metres, positive) in one scan (sensor frame, z up):
    the most common height among the lowest returns of the :data:`GROUND_CELLS` BEV cells nearest
    the vehicle (beyond :data:`GROUND_FROM`, below the sensor); None when too few cells or no
    height stands out (a scan in another frame, no ground in view)."""
    xyz = np.asarray(points)[:, :3].astype(np.float64)
    xyz = xyz[np.isfinite(xyz).all(axis=1)]
    r = np.hypot(xyz[:, 0], xyz[:, 1])
    keep = (r >= GROUND_FROM) & (xyz[:, 2] <= -MOUNT_RANGE[0]) & (xyz[:, 2] >= -MOUNT_RANGE[1])
    xyz, r = xyz[keep], r[keep]
    if len(xyz) < 100:
        return None
    cell = np.floor(xyz[:, :2] / GROUND_CELL).astype(np.int64) + 2**15
    key = cell[:, 0] * 2**16 + cell[:, 1]
    # one sort by cell, then by height (millimetres below MOUNT_RANGE's top): each cell's lowest first
    depth = np.round((xyz[:, 2] + MOUNT_RANGE[1]) * 1000.0).astype(np.int64)
    order = np.argsort(key * 2**13 + depth)
    sorted_key = key[order]
    first = order[np.r_[True, sorted_key[1:] != sorted_key[:-1]]]
    lowest, reach = xyz[first, 2], r[first]
    if len(lowest) < 20:
        return None
    if len(lowest) > GROUND_CELLS:
        lowest = lowest[np.argpartition(reach, GROUND_CELLS)[:GROUND_CELLS]]
    edges = np.arange(-MOUNT_RANGE[1], -MOUNT_RANGE[0] + GROUND_BIN, GROUND_BIN)
    counts, _ = np.histogram(lowest, edges)
    peak = int(np.argmax(counts))
    if counts[peak] < max(5, len(lowest) // 10):
        return None
    in_peak = lowest[(lowest >= edges[max(peak - 1, 0)]) & (lowest < edges[min(peak + 2, len(edges) - 1)])]
    return float(-np.median(in_peak))


def ring_column(points: np.ndarray, fields) -> np.ndarray | None:
    """The ``ring`` column of ``points`` whose columns are named ``fields`` (a
    :class:`~pcc_ros.types.Sample`'s), or None when it has none."""
    fields = tuple(fields)
    return np.asarray(points)[:, fields.index("ring")] if "ring" in fields else None


def sensor_for(name: str, points: np.ndarray, rings: np.ndarray | None = None) -> SensorModel:
    """A one-frame beam model (offline callers without a :class:`BeamModel`): the named preset,
    or for ``auto`` the frame's estimate (the :data:`FALLBACK` preset when it shows none)."""
    if name != AUTO:
        return sensor_preset(name)
    return estimate_sensor(points, rings) or SENSOR_PRESETS[FALLBACK]
