"""Compiled inner loop of the filter's profile terms (:mod:`pcc_ros.pipeline.evidence_profile`).

Why compiled: each (point, box) candidate pair of the grown boxes is tested, sorted into body /
above / shell and, for a body return, gives an azimuth and a depth behind the box's near face: a
dozen float operations per pair, tens of thousands of pairs per frame, visited once (the pairs
are never gathered into arrays; the candidates are the box's cells of the scan's BEV index,
:mod:`pcc_ros.pipeline.evidence_index`). As numpy passes over the pair arrays
they cost more than the rays of :mod:`pcc_ros.pipeline.evidence` (``pcc bench filter``); here
each pair is visited once, without the GIL (:func:`pcc_ros.jit.compiled`, cached on disk,
compiled by :func:`pcc_ros.pipeline.evidence.warm_up`).
"""

from __future__ import annotations

import math

import numpy as np
from numba.cpython.unsafe.numbers import trailing_zeros  # LLVM's cttz

from pcc_ros.jit import compiled

# Columns of :func:`profile_cells`' per-box output.
BODY, ABOVE, SHELL, AZ_MIN, AZ_MAX, DEPTH_SUM, TOP, MID, CORNER = range(9)


@compiled()
def profile_cells(x, y, z, order, start, run_first, run_last, run_ends, test, cz, half, origin, centre_az, z_shift,
                  face_margin, ground, azimuth, corner, out, share, marks):
    """The profile counts of every box from the candidates of its cell runs in the scan's index
    (:mod:`pcc_ros.pipeline.evidence_index`: ``order``, ``start``; box ``b``'s runs end at
    ``run_ends[b]``), each candidate tested and used in one visit: the exact test of
    :meth:`pcc_ros.geometry.boxes.BoxCandidates.pairs` against the grown box's ``test`` row
    (``zlo, zhi, cx, cy, cos, sin, half length, half width`` in the scan's precision, ``cz`` its
    centre height in that precision; same operations, same roundings), the box-frame coordinates
    it gives (the height shifted by ``z_shift`` into the box's own frame), then per box ``b``
    (``half``, ``origin``, ``centre_az``: the box's own, not the grown one's): counts of body,
    above and shell returns, the min / max azimuth of the body returns relative to
    ``centre_az[b]``, the sum of their depth shares behind the near face, the highest body return
    (rows of ``out``, columns :data:`BODY` ...; ``out`` zeroed by the caller, ``AZ_MIN`` / ``AZ_MAX``
    / ``TOP`` are set only where a body return exists; the azimuths, an ``atan2`` per body return,
    only with ``azimuth``: ``fill`` alone reads them).

    The depth shares are summed in ascending point order, whatever order the cells hand them
    over in (a float sum depends on its order): each body return's share goes to ``share`` (as
    long as the scan) and its bit to ``marks`` (a bit per point, all clear; left clear), and the
    box's marked points are summed by a sweep over the words it touched.

    ``corner`` (``(corner_length, corner_width, band_top)``, shares of the box; an empty array:
    not measured): ``MID`` counts the body returns up to ``band_top`` of the box height, ``CORNER``
    those of them in the box's four vertical corner columns (``|x| >= (1 - 2 corner_length)``
    of the half length and ``|y| >= (1 - 2 corner_width)`` of the half width)."""
    measure_corner = len(corner) == 3
    one = np.uint64(1)
    begin = 0
    for b in range(len(run_ends)):
        az_min, az_max, top = np.inf, -np.inf, -np.inf
        hx, hy, hz = half[b, 0] + face_margin, half[b, 1] + face_margin, half[b, 2]
        zlo = -hz + ground
        ox, oy, oz = origin[b, 0], origin[b, 1], origin[b, 2]
        word_lo, word_hi = len(marks), -1
        for r in range(begin, run_ends[b]):
            for k in range(start[run_first[r]], start[run_last[r] + 1]):
                i = order[k]
                pz = z[i]
                if not (pz >= test[b, 0] and pz <= test[b, 1]):
                    continue
                dx = x[i] - test[b, 2]
                dy = y[i] - test[b, 3]
                gx = test[b, 4] * dx + test[b, 5] * dy
                gy = test[b, 4] * dy - test[b, 5] * dx
                if not (abs(gx) <= test[b, 6] and abs(gy) <= test[b, 7]):
                    continue
                px = np.float64(gx)
                py = np.float64(gy)
                pzb = np.float64(pz - cz[b]) + z_shift
                over = abs(px) <= hx and abs(py) <= hy
                in_band = zlo <= pzb <= hz
                if over and in_band:
                    out[b, BODY] += 1
                    if azimuth:
                        a = math.atan2(np.float64(y[i]), np.float64(x[i])) - centre_az[b]
                        if a > math.pi:
                            a -= 2 * math.pi
                        elif a < -math.pi:
                            a += 2 * math.pi
                        az_min = min(az_min, a)
                        az_max = max(az_max, a)
                    top = max(top, pzb)
                    if measure_corner and pzb <= half[b, 2] * (2.0 * corner[2] - 1.0):
                        out[b, MID] += 1
                        if (abs(px) >= half[b, 0] * (1.0 - 2.0 * corner[0])
                                and abs(py) >= half[b, 1] * (1.0 - 2.0 * corner[1])):
                            out[b, CORNER] += 1
                    # the ray from the sensor (t = 0) to the return (t = 1): where it enters and
                    # leaves the box (slabs), and how deep between the two the return lies
                    near = -np.inf
                    far = np.inf
                    for d, o, h_lo, h_hi in ((px - ox, ox, -hx, hx), (py - oy, oy, -hy, hy), (pzb - oz, oz, zlo, hz)):
                        if d != 0.0:
                            t0 = (h_lo - o) / d
                            t1 = (h_hi - o) / d
                            near = max(near, min(t0, t1))
                            far = min(far, max(t0, t1))
                    depth = (1.0 - near) / max(far - near, 1e-9)
                    share[i] = min(max(depth, 0.0), 1.0)
                    w = i >> 6
                    marks[w] |= one << np.uint64(i & 63)
                    word_lo = min(word_lo, w)
                    word_hi = max(word_hi, w)
                elif over and pzb > hz:
                    out[b, ABOVE] += 1
                elif in_band and not over:
                    out[b, SHELL] += 1
        begin = run_ends[b]
        total = 0.0
        for w in range(word_lo, word_hi + 1):
            word = marks[w]
            while word:
                total += share[(w << 6) + np.int64(trailing_zeros(word))]
                word &= word - one
            marks[w] = 0
        out[b, DEPTH_SUM] = total
        if out[b, BODY]:
            out[b, AZ_MIN] = az_min
            out[b, AZ_MAX] = az_max
            out[b, TOP] = top
