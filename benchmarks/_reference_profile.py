"""The filter's profile pass as it was before its pairs were tested in the compiled loop
(commit 24858c5, kept verbatim apart from names): :class:`~pcc_ros.geometry.boxes.BoxCandidates`
gathers the pairs of the grown boxes into arrays (``pairs(local=True)``), the compiled loop then
reads them box by box, and the overlap clips every pair of boxes whose circles meet. The
reference ``pcc bench filter`` checks the profile terms against (bit for bit) and times beside
them; nothing else uses it.
"""

from __future__ import annotations

import math
from collections.abc import Collection

import numpy as np

from pcc_ros.geometry.beams import SensorModel
from pcc_ros.geometry.boxes import BoxCandidates, iou_bev
from pcc_ros.geometry.canonical import to_box_local
from pcc_ros.jit import compiled
from pcc_ros.pipeline.evidence import EVIDENCE_GROUND, angular_window
from pcc_ros.pipeline.evidence_profile import (
    ABOVE_PRIOR_RETURNS,
    ABOVE_REACH,
    DEPTH_PRIOR,
    DEPTH_PRIOR_RETURNS,
    FACE_MARGIN,
    PROFILE_TERMS,
    SHELL,
)
from pcc_ros.types import Boxes

BODY, ABOVE, SHELL_COL, AZ_MIN, AZ_MAX, DEPTH_SUM, TOP = range(7)


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
        out[b, SHELL_COL] = shell
        out[b, DEPTH_SUM] = depth
        if body:
            out[b, AZ_MIN] = az_min
            out[b, AZ_MAX] = az_max
            out[b, TOP] = top


def covered_share(boxes: Boxes) -> np.ndarray:
    """Per box, the largest share of its BEV footprint that a box with a higher score (ties:
    an earlier box) covers: the duplicate check an NMS would make, measured, not applied."""
    n = len(boxes)
    if n < 2:
        return np.zeros(n)
    iou = iou_bev(boxes, boxes)
    area = boxes.size[:, 0] * boxes.size[:, 1]
    # intersection from IoU: I = IoU * (A_i + A_j) / (1 + IoU)
    inter = iou * (area[:, None] + area[None, :]) / (1.0 + iou)
    score = np.nan_to_num(np.asarray(boxes.score, dtype=np.float64), nan=-np.inf)
    idx = np.arange(n)
    better = (score[None, :] > score[:, None]) | ((score[None, :] == score[:, None]) & (idx[None, :] < idx[:, None]))
    share = np.where(better, inter / np.maximum(area[:, None], 1e-12), 0.0)
    return np.clip(share.max(axis=1), 0.0, 1.0)


def profile_terms(points: np.ndarray, boxes: Boxes, sensor: SensorModel,
                  measure: Collection[str] | None = None) -> dict[str, np.ndarray]:
    """``above``, ``fill``, ``spill``, ``overlap``, ``depth`` and ``top`` of every box (module
    docstring), plus the raw counts behind them (``n_body``, ``n_above``, ``n_shell``).

    ``depth``: how deep behind the box's near surface its body returns lie, as a share of the
    box's depth along each return's ray (0: where the ray enters the box, 1: its far side),
    averaged with one prior return at 0.5 (no return: 0.5, undecided). A car fills its box: the
    rays stop at its faces; a pole, a pedestrian or a bollard in a car box stops them deep
    inside; a box shifted off its car holds the car's returns at its back. ``top``: the highest
    body return over the box bottom, as a share of the box height (0 without one).

    ``measure``: the terms wanted (default all); only they are returned, with the same values.
    ``overlap`` alone needs no pass over the scan; without ``spill`` the boxes grow sideways by
    the face margin only, not by the shell (about half the candidate pairs of a car box)."""
    wanted = set(PROFILE_TERMS if measure is None else measure) & set(PROFILE_TERMS)
    n = len(boxes)
    if n == 0:
        zero = np.zeros(0)
        return {k: zero for k in (*sorted(wanted), "n_body", "n_above", "n_shell")}
    out_terms: dict[str, np.ndarray] = {"overlap": covered_share(boxes)} if "overlap" in wanted else {}
    if not wanted - {"overlap"}:
        return out_terms
    centre, size = boxes.center.copy(), boxes.size.copy()
    # (without the shell, a 5 cm slack past the face margin: the kernel's body test of a point
    # on that boundary must never depend on the rounding of the grown box's half size)
    size[:, :2] += 2 * ((SHELL if "spill" in wanted else 0.05) + FACE_MARGIN)
    size[:, 2] += ABOVE_REACH
    centre[:, 2] += ABOVE_REACH / 2
    grown = Boxes(centre, size, boxes.yaw)
    candidates = BoxCandidates(points, grown)
    pair_point, starts, (lx, ly, lz) = candidates.pairs(local=True)
    cos, sin = np.cos(boxes.yaw), np.sin(boxes.yaw)
    cx, cy, cz = boxes.center.T
    origin = np.ascontiguousarray(np.stack(to_box_local(0.0, 0.0, 0.0, cx, cy, cz, cos, sin), axis=1))
    centre_az = np.arctan2(cy, cx)
    pts = candidates.points
    px, py = np.ascontiguousarray(pts[:, 0]), np.ascontiguousarray(pts[:, 1])
    out = np.zeros((n, 7))
    profile_pairs(lx, ly, lz, px, py, pair_point, starts, np.ascontiguousarray(boxes.size / 2), origin,
                  centre_az, ABOVE_REACH / 2, FACE_MARGIN, EVIDENCE_GROUND, out)
    n_body, n_above, n_shell = out[:, BODY], out[:, ABOVE], out[:, SHELL_COL]
    has = n_body > 0
    az_lo, az_hi, *_ = angular_window(boxes)
    step = np.deg2rad(sensor.azimuth_resolution_deg)
    span = out[:, AZ_MAX] - out[:, AZ_MIN]
    fill = np.where(has, np.clip((span + step) / (az_hi - az_lo + step), 0.0, 1.0), 0.0)
    top = np.where(has, (out[:, TOP] + boxes.size[:, 2] / 2) / boxes.size[:, 2], 0.0)
    terms = {
        # the terms as the pipeline defines them now (their priors): only the pass is 24858c5's
        "above": n_above / (n_above + n_body + ABOVE_PRIOR_RETURNS),
        "fill": fill,
        "spill": np.log((n_shell + 1.0) / (n_body + 1.0)),
        "depth": (out[:, DEPTH_SUM] + DEPTH_PRIOR * DEPTH_PRIOR_RETURNS) / (n_body + DEPTH_PRIOR_RETURNS),
        "top": top,
    }
    out_terms.update({k: v for k, v in terms.items() if k in wanted})
    out_terms.update({"n_body": n_body, "n_above": n_above})
    if "spill" in wanted:
        out_terms["n_shell"] = n_shell
    return out_terms
