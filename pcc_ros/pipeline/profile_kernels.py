"""Compiled inner loop of the filter's profile terms (:mod:`pcc_ros.pipeline.evidence_profile`).

Why compiled: each (point, box) pair of the grown boxes is sorted into body / above / shell and,
for a body return, gives an azimuth and a depth behind the box's near face: a dozen float
operations per pair, tens of thousands of pairs per frame. As numpy passes over the pair arrays
they cost more than the rays of :mod:`pcc_ros.pipeline.evidence` (``pcc bench filter``); here
each pair is visited once, without the GIL (:func:`pcc_ros.jit.compiled`, cached on disk,
compiled by :func:`pcc_ros.pipeline.evidence.warm_up`).
"""

from __future__ import annotations

import math

import numpy as np

from pcc_ros.jit import compiled

# Columns of :func:`profile_pairs`' per-box output.
BODY, ABOVE, SHELL, AZ_MIN, AZ_MAX, DEPTH_SUM, TOP = range(7)


@compiled()
def profile_pairs(lx, ly, lz, px, py, pair_point, starts, half, origin, centre_az, z_shift, face_margin, ground,
                  out):
    """Per box ``b`` (its pairs ``starts[b]:starts[b + 1]``; ``lx, ly, lz`` box-frame coordinates
    of the grown box, ``z_shift`` added to ``lz`` gives the height in the box's own frame;
    ``px, py`` the scan's x / y, indexed by ``pair_point``): counts of body, above and shell
    returns, the min / max azimuth of the body returns relative to ``centre_az[b]``, the sum of
    their depth shares behind the near face, the highest body return (rows of ``out``, columns
    :data:`BODY` ...; ``out`` zeroed by the caller, ``AZ_MIN`` / ``AZ_MAX`` / ``TOP`` are set
    only where a body return exists)."""
    n = len(starts) - 1
    for b in range(n):
        hx, hy, hz = half[b, 0] + face_margin, half[b, 1] + face_margin, half[b, 2]
        ox, oy, oz = origin[b, 0], origin[b, 1], origin[b, 2]
        zlo = -hz + ground
        body = 0
        above = 0
        shell = 0
        az_min = np.inf
        az_max = -np.inf
        depth = 0.0
        top = -np.inf
        for k in range(starts[b], starts[b + 1]):
            x = np.float64(lx[k])
            y = np.float64(ly[k])
            z = np.float64(lz[k]) + z_shift
            over = abs(x) <= hx and abs(y) <= hy
            in_band = zlo <= z <= hz
            if over and in_band:
                body += 1
                i = pair_point[k]
                a = math.atan2(np.float64(py[i]), np.float64(px[i])) - centre_az[b]
                if a > math.pi:
                    a -= 2 * math.pi
                elif a < -math.pi:
                    a += 2 * math.pi
                az_min = min(az_min, a)
                az_max = max(az_max, a)
                top = max(top, z)
                # the ray from the sensor (t = 0) to the return (t = 1): where it enters and
                # leaves the box (slabs), and how deep between the two the return lies
                near = -np.inf
                far = np.inf
                for d, o, h_lo, h_hi in ((x - ox, ox, -hx, hx), (y - oy, oy, -hy, hy), (z - oz, oz, zlo, hz)):
                    if d != 0.0:
                        t0 = (h_lo - o) / d
                        t1 = (h_hi - o) / d
                        near = max(near, min(t0, t1))
                        far = min(far, max(t0, t1))
                share = (1.0 - near) / max(far - near, 1e-9)
                depth += min(max(share, 0.0), 1.0)
            elif over and z > hz:
                above += 1
            elif in_band and not over:
                shell += 1
        out[b, BODY] = body
        out[b, ABOVE] = above
        out[b, SHELL] = shell
        out[b, DEPTH_SUM] = depth
        if body:
            out[b, AZ_MIN] = az_min
            out[b, AZ_MAX] = az_max
            out[b, TOP] = top
