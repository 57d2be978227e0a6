"""Ray-cast scenes for the filter's tests: every beam of a sensor model against a flat ground, a
far wall, boxes and ellipsoids, with the box of a car body standing on that ground."""

from __future__ import annotations

import numpy as np

from pcc_ros.geometry.beams import SENSOR_PRESETS
from pcc_ros.types import Boxes

SENSOR = SENSOR_PRESETS["hdl64"]
GROUND_Z = -1.73


def cast(targets=(), sensor=SENSOR, max_range: float = 80.0, ellipsoids=()) -> np.ndarray:
    """A synthetic scan: every beam of ``sensor`` (azimuth within +-60 deg) hits the first of a
    flat ground, a wall at x = 40 m, the axis-aligned boxes ``targets`` [(lo, hi), ...] and the
    axis-aligned ellipsoids ``ellipsoids`` [(centre, radii), ...] (a vegetation blob)."""
    el = sensor.ring_elevations()
    az = np.deg2rad(np.arange(-60.0, 60.0, sensor.azimuth_resolution_deg))
    e, a = np.meshgrid(el, az, indexing="ij")
    d = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1).reshape(-1, 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(d[:, 2] < 0, GROUND_Z / d[:, 2], np.inf)
        t = np.minimum(t, np.where(d[:, 0] > 0, 40.0 / d[:, 0], np.inf))
        for lo, hi in targets:
            lo, hi = np.asarray(lo, float), np.asarray(hi, float)
            t1, t2 = lo / d, hi / d
            tn = np.fmax.reduce(np.minimum(t1, t2), axis=1)
            tf = np.fmin.reduce(np.maximum(t1, t2), axis=1)
            hit = (tf >= tn) & (tn > 0)
            t = np.where(hit, np.minimum(t, tn), t)
        for centre, radii in ellipsoids:
            # |(t d - c) / r|^2 = 1: a quadratic in t, the nearer root
            u, c = d / radii, np.asarray(centre, float) / radii
            qa, qb, qc = (u * u).sum(1), -2 * (u @ c), c @ c - 1.0
            disc = qb * qb - 4 * qa * qc
            root = (-qb - np.sqrt(disc)) / (2 * qa)
            t = np.where((disc >= 0) & (root > 0), np.minimum(t, root), t)
    ok = np.isfinite(t) & (t < max_range)
    return (d[ok] * t[ok, None]).astype(np.float32)


CAR_LO, CAR_HI = (14.0, -0.9, GROUND_Z + 0.3), (18.2, 0.9, GROUND_Z + 1.5)  # a car body (no wheels)
BOX = Boxes([[16.1, 0.0, GROUND_Z + 0.75]], [[4.2, 1.8, 1.5]], [0.0], ["Car"], [0.3])
