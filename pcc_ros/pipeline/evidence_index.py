"""The bird's-eye-view index of the scan that the evidence filter's footprint queries share: the
local ground (:mod:`pcc_ros.pipeline.evidence`) and the profile pass
(:mod:`pcc_ros.pipeline.evidence_profile`).

One grid over the boxes of every query; each query's boxes list the cells that can hold a
point they contain (the cell centre within the box grown by half a cell diagonal and a slack);
one compiled pass gives every point its cell, a counting sort groups the points of the listed
cells within the queries' union height range, and each box's cells are runs of the sorted points
(one run per grid column: the listed cells of a column are consecutive). The index only selects a
superset of the points a query's exact test (in the scan's precision) accepts, so it changes no
value; both queries read the same sort, so the scan is sorted once for the two.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pcc_ros.scratch import Scratch

#: BEV cell (metres) of the index (coarsened when the boxes spread so far that the grid would
#: exceed :data:`MAX_CELLS`).
CELL = 1.0
#: Cells of the grid at most (the counting sort's table of cell starts).
MAX_CELLS = 32_000
#: Slack (metres) of the cell test: a point the exact test (in the scan's precision) accepts
#: lies in a cell listed for the box even after float32 rounding.
SLACK = 0.01


@dataclass(frozen=True)
class Footprints:
    """A query's boxes as the index sees them: BEV centre, yaw's cosine and sine (float64), half
    length and width (metres), and the lowest and highest height any of them tests."""

    cx: np.ndarray
    cy: np.ndarray
    cos: np.ndarray
    sin: np.ndarray
    hl: np.ndarray
    hw: np.ndarray
    zmin: float
    zmax: float

    def extents(self) -> tuple[np.ndarray, np.ndarray]:
        """Half extents (x, y) of each footprint's axis-aligned bounding rectangle."""
        ac, as_ = np.abs(self.cos), np.abs(self.sin)
        return ac * self.hl + as_ * self.hw, as_ * self.hl + ac * self.hw


@dataclass
class BevIndex:
    """The sorted scan (``order``, grouped by cell; ``start``: each cell's first slot) and, per
    query, its boxes' cell runs ``(run_first, run_last, run_ends)``: box ``b``'s runs are
    ``run_ends[b - 1] .. run_ends[b]``, run ``r`` the cells ``run_first[r] .. run_last[r]``."""

    order: np.ndarray
    start: np.ndarray
    runs: list[tuple[np.ndarray, np.ndarray, np.ndarray]]


def bev_index(x: np.ndarray, y: np.ndarray, z: np.ndarray, queries: list[Footprints], ws: Scratch) -> BevIndex:
    """The index of the scan's coordinate columns (contiguous, one dtype) for ``queries``
    (non-empty box sets). Off-grid and NaN points clamp into the grid's border, which no box
    lists; points outside ``[min zmin, max zmax]`` (and NaN heights) are never placed."""
    from pcc_ros.pipeline import evidence_kernels as kernels  # numba: heavy, only when measuring

    dt = x.dtype.type
    extents = [q.extents() for q in queries]
    lo = np.array([[np.min(q.cx - ex), np.min(q.cy - ey)] for q, (ex, ey) in zip(queries, extents)]).min(axis=0)
    hi = np.array([[np.max(q.cx + ex), np.max(q.cy + ey)] for q, (ex, ey) in zip(queries, extents)]).max(axis=0)
    cell = CELL
    span = hi - lo
    while np.prod(np.floor(span / cell) + 5) > MAX_CELLS:  # boxes spread far apart: coarser cells
        cell *= 1.5
    # two cells of margin on every side: a point off the grid is off every box
    origin = lo - 2 * cell
    nx, ny = (int(v) for v in np.floor(span / cell) + 5)
    listed = np.zeros(nx * ny, dtype=bool)
    grow = cell * np.sqrt(0.5) + SLACK
    runs = []
    for q in queries:
        # one run per grid column a box's bounding rectangle (widened by a cell) spans at most
        first, last = ws(f"runs_first{len(runs)}", len(q.cx) * nx, np.int64), ws(f"runs_last{len(runs)}",
                                                                             len(q.cx) * nx, np.int64)
        ends = np.zeros(len(q.cx), dtype=np.int64)
        count = kernels.cell_runs(q.cx, q.cy, q.cos, q.sin, q.hl, q.hw, float(origin[0]), float(origin[1]), cell,
                                  nx, ny, grow, listed, first, last, ends)
        runs.append((first[:count], last[:count], ends))
    key = ws("bev_cell", len(x), np.int32)
    start, order = ws("bev_start", nx * ny + 1, np.int64), ws("bev_order", len(x), np.int64)
    zmin, zmax = min(q.zmin for q in queries), max(q.zmax for q in queries)
    kernels.ground_cells(x, y, z, dt(origin[0]), dt(origin[1]), dt(1.0 / cell), nx, ny, dt(zmin), dt(zmax), key)
    kernels.counting_sort(key, listed, start, order)
    return BevIndex(order, start, runs)
