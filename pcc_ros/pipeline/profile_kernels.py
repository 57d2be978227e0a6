"""Compiled inner loop of the filter's profile terms (:mod:`pcc_ros.pipeline.evidence_profile`).

Why compiled: each (point, box) candidate pair of the grown boxes is tested, sorted into body /
above / shell and, for a body return, gives an azimuth and a depth behind the box's near face: a
dozen float operations per pair, tens of thousands of pairs per frame, visited once (the pairs
are never gathered into arrays). As numpy passes over the pair arrays
they cost more than the rays of :mod:`pcc_ros.pipeline.evidence` (``pcc bench filter``); here
each pair is visited once, without the GIL (:func:`pcc_ros.jit.compiled`, cached on disk,
compiled by :func:`pcc_ros.pipeline.evidence.warm_up`).
"""

from __future__ import annotations

import math

import numpy as np

from pcc_ros.jit import compiled

# Columns of :func:`profile_pairs`' per-box output.
BODY, ABOVE, SHELL, AZ_MIN, AZ_MAX, DEPTH_SUM, TOP, MID, CORNER = range(9)


@compiled()
def profile_pairs(pair_point, pair_box, pts, test, cz, half, origin, centre_az, z_shift, face_margin, ground, azimuth,
                  corner, out):
    """The profile counts of every box from the candidate pairs of the grown boxes
    (:meth:`pcc_ros.geometry.boxes.BoxCandidates.candidate_test`: ``pair_point``, ``pair_box``,
    the scan ``pts`` and each grown box's ``test`` row in the test's precision, ``cz`` its centre
    height in that precision), each pair tested and used in one visit: the exact test of
    :meth:`~pcc_ros.geometry.boxes.BoxCandidates.pairs` (same operations, same roundings), the
    box-frame coordinates it gives (the height shifted by ``z_shift`` into the box's own frame),
    then per box ``b`` (``half``, ``origin``, ``centre_az``: the box's own, not the grown one's):
    counts of body, above and shell returns, the min / max azimuth of the body returns relative to
    ``centre_az[b]``, the sum of their depth shares behind the near face (summed in point order),
    the highest body return (rows of ``out``, columns :data:`BODY` ...; ``out`` zeroed by the
    caller, ``AZ_MIN`` / ``AZ_MAX`` / ``TOP`` are set only where a body return exists; the
    azimuths, an ``atan2`` per body return, only with ``azimuth``: ``fill`` alone reads them).

    ``corner`` (``(corner_length, corner_width, band_top)``, shares of the box; an empty array:
    not measured): ``MID`` counts the body returns up to ``band_top`` of the box height, ``CORNER``
    those of them in the box's four vertical corner columns (``|x| >= (1 - 2 corner_length)``
    of the half length and ``|y| >= (1 - 2 corner_width)`` of the half width)."""
    nb = len(half)
    az_min = np.full(nb, np.inf)
    az_max = np.full(nb, -np.inf)
    top = np.full(nb, -np.inf)
    measure_corner = len(corner) == 3
    for k in range(len(pair_point)):
        i = pair_point[k]
        b = pair_box[k]
        pz = pts[i, 2]
        if not (pz >= test[b, 0] and pz <= test[b, 1]):
            continue
        dx = pts[i, 0] - test[b, 2]
        dy = pts[i, 1] - test[b, 3]
        gx = test[b, 4] * dx + test[b, 5] * dy
        gy = test[b, 4] * dy - test[b, 5] * dx
        if not (abs(gx) <= test[b, 6] and abs(gy) <= test[b, 7]):
            continue
        x = np.float64(gx)
        y = np.float64(gy)
        z = np.float64(pz - cz[b]) + z_shift
        hx, hy, hz = half[b, 0] + face_margin, half[b, 1] + face_margin, half[b, 2]
        zlo = -hz + ground
        over = abs(x) <= hx and abs(y) <= hy
        in_band = zlo <= z <= hz
        if over and in_band:
            out[b, BODY] += 1
            if azimuth:
                a = math.atan2(np.float64(pts[i, 1]), np.float64(pts[i, 0])) - centre_az[b]
                if a > math.pi:
                    a -= 2 * math.pi
                elif a < -math.pi:
                    a += 2 * math.pi
                az_min[b] = min(az_min[b], a)
                az_max[b] = max(az_max[b], a)
            top[b] = max(top[b], z)
            if measure_corner and z <= half[b, 2] * (2.0 * corner[2] - 1.0):
                out[b, MID] += 1
                if abs(x) >= half[b, 0] * (1.0 - 2.0 * corner[0]) and abs(y) >= half[b, 1] * (1.0 - 2.0 * corner[1]):
                    out[b, CORNER] += 1
            # the ray from the sensor (t = 0) to the return (t = 1): where it enters and
            # leaves the box (slabs), and how deep between the two the return lies
            ox, oy, oz = origin[b, 0], origin[b, 1], origin[b, 2]
            near = -np.inf
            far = np.inf
            for d, o, h_lo, h_hi in ((x - ox, ox, -hx, hx), (y - oy, oy, -hy, hy), (z - oz, oz, zlo, hz)):
                if d != 0.0:
                    t0 = (h_lo - o) / d
                    t1 = (h_hi - o) / d
                    near = max(near, min(t0, t1))
                    far = min(far, max(t0, t1))
            share = (1.0 - near) / max(far - near, 1e-9)
            out[b, DEPTH_SUM] += min(max(share, 0.0), 1.0)
        elif over and z > hz:
            out[b, ABOVE] += 1
        elif in_band and not over:
            out[b, SHELL] += 1
    for b in range(nb):
        if out[b, BODY]:
            out[b, AZ_MIN] = az_min[b]
            out[b, AZ_MAX] = az_max[b]
            out[b, TOP] = top[b]
