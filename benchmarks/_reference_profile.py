"""The filter's profile pass as it was before its pairs were tested in the compiled loop
(commit 24858c5, the loop and the overlap kept verbatim apart from names):
:class:`~pcc_ros.geometry.boxes.BoxCandidates` gathers the pairs of the grown boxes into arrays
(``pairs(local=True)``), the compiled loop then reads them box by box, and the overlap clips every
pair of boxes. What the pass feeds on and what is derived from its counts (the grown boxes, the
box frames, the terms) is the pipeline's own, so only the pass differs. The reference ``pcc bench
filter`` checks the profile terms against (bit for bit) and times beside them; nothing else uses it.
"""

from __future__ import annotations

import math
from collections.abc import Collection

import numpy as np

from pcc_ros.geometry.beams import SensorModel
from pcc_ros.geometry.boxes import BoxCandidates, iou_bev
from pcc_ros.jit import compiled
from pcc_ros.pipeline.evidence import EVIDENCE_GROUND
from pcc_ros.pipeline.evidence_profile import (
    ABOVE_REACH,
    FACE_MARGIN,
    PROFILE_TERMS,
    box_frames,
    grown_boxes,
    terms_from_counts,
)
from pcc_ros.pipeline.profile_kernels import ABOVE, AZ_MAX, AZ_MIN, BODY, DEPTH_SUM, SHELL, TOP
from pcc_ros.types import Boxes


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
    """:func:`pcc_ros.pipeline.evidence_profile.profile_terms` with 24858c5's pass (pairs gathered
    into arrays, then the loop above) and its overlap; the grown boxes and the terms derived from
    the pass's counts are the pipeline's own (:func:`~pcc_ros.pipeline.evidence_profile.grown_boxes`,
    :func:`~pcc_ros.pipeline.evidence_profile.terms_from_counts`), so the two agree wherever the
    passes do."""
    # (``corner`` is newer than 24858c5: its pass had no counterpart)
    wanted = (set(PROFILE_TERMS if measure is None else measure) & set(PROFILE_TERMS)) - {"corner"}
    n = len(boxes)
    if n == 0:
        zero = np.zeros(0)
        return {k: zero for k in (*sorted(wanted), "n_body", "n_above", "n_shell")}
    out_terms: dict[str, np.ndarray] = {"overlap": covered_share(boxes)} if "overlap" in wanted else {}
    if not wanted - {"overlap"}:
        return out_terms
    candidates = BoxCandidates(points, grown_boxes(boxes, "spill" in wanted))
    pair_point, starts, (lx, ly, lz) = candidates.pairs(local=True)
    origin, centre_az = box_frames(boxes)
    pts = candidates.points
    px, py = np.ascontiguousarray(pts[:, 0]), np.ascontiguousarray(pts[:, 1])
    out = np.zeros((n, 7))
    profile_pairs(lx, ly, lz, px, py, pair_point, starts, np.ascontiguousarray(boxes.size / 2), origin,
                  centre_az, ABOVE_REACH / 2, FACE_MARGIN, EVIDENCE_GROUND, out)
    return {**out_terms, **terms_from_counts(out, boxes, sensor, wanted)}
