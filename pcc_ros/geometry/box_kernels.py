"""Compiled pass of :class:`pcc_ros.geometry.boxes.BoxCandidates` over the scan.

Why compiled: the pass hashes every point of the scan into the BEV grid over the boxes and
looks its cell up; as numpy passes over blocks of the scan it took ten passes through memory
(subtract, scale, clip, truncate and combine the two axes, look up, compare, select, gather),
most of the crop stage and of the filter's profile pass for a 120k-point scan. Here each point
is visited once, without the GIL (:func:`pcc_ros.jit.compiled`, cached on disk).
"""

from __future__ import annotations

import numpy as np

from pcc_ros.jit import compiled


@compiled()
def scan_cells(pts, ox, oy, inv, nx, ny, row_of, zmin, zmax, hit, hit_row):
    """The points of ``pts`` (x, y, z first) in a cell some box lists and within ``[zmin,
    zmax]``: their indices (ascending) into ``hit``, their table rows into ``hit_row``; returns
    how many. The cell as the numpy pass computed it, in float32: ``(float32(x) - ox) * inv``
    clipped onto ``[0, nx - 1]`` (``ny - 1`` for y), truncated; a NaN coordinate lies in no
    cell (numpy's pass sent it to the grid's empty border)."""
    m = 0
    for i in range(pts.shape[0]):
        fx = (np.float32(pts[i, 0]) - ox) * inv
        fy = (np.float32(pts[i, 1]) - oy) * inv
        if fx != fx or fy != fy:
            continue
        gx = 0 if fx < 0 else (nx - 1 if fx > nx - 1 else int(fx))
        gy = 0 if fy < 0 else (ny - 1 if fy > ny - 1 else int(fy))
        row = row_of[gx * ny + gy]
        if row != 0:
            z = pts[i, 2]
            if z >= zmin and z <= zmax:
                hit[m] = i
                hit_row[m] = row
                m += 1
    return m
