"""The evidence filter's profile terms: where a box's returns lie, not only how many there are.

The ray terms of :mod:`pcc_ros.pipeline.evidence` say whether *something* solid fills a box.
A pole, a sign, a pedestrian or a bush inside a car-sized box is solid too; a box shifted off
its car still holds part of the car. These terms look at the arrangement of the returns in and
around each box (definitions in ``docs/filter.md``, "Profile terms"):

* ``above``: the share of the returns over the box footprint, from :data:`EVIDENCE_GROUND`
  above the bottom to :data:`ABOVE_REACH` over the top, that lie above the top. A car has sky
  over its roof; a pole, sign, tree or lamp post continues upward.
* ``fill``: the azimuth span of the in-box returns over the box's own azimuth span seen from
  the sensor, both widened by one azimuth step of the beam model (so a far car a few columns
  wide is not punished for the sensor's resolution). A car's visible faces cover its whole
  silhouette; a pole, bollard or pedestrian covers a sliver of it.
* ``spill``: log of (returns in a shell :data:`SHELL` metres wide around the box's sides, at
  body height + 1) / (returns in the box at body height + 1). A box displaced off its car has
  the car's returns straddling a face; a box on a car has them inside.
* ``overlap``: the largest share of the box's footprint covered by another box of the frame
  with a higher detector score (ties: the earlier box). A duplicate the detector's NMS let
  through; only the order of the scores is used, never their scale.

All four are dimensionless and read the scan geometry only through the sensor's azimuth step
(the beam model's), so one weight set serves every sensor. One vectorised pass of
:class:`pcc_ros.geometry.boxes.BoxCandidates` over the scan against the boxes grown by the
shell and the reach above.
"""

from __future__ import annotations

import numpy as np

from pcc_ros.geometry.beams import SensorModel
from pcc_ros.geometry.boxes import BoxCandidates, iou_bev
from pcc_ros.geometry.canonical import to_box_local
from pcc_ros.pipeline.evidence import EVIDENCE_GROUND, angular_window
from pcc_ros.types import Boxes

#: The profile terms, in the order :func:`profile_terms` returns them.
PROFILE_TERMS = ("above", "fill", "spill", "overlap", "depth", "top")
#: Metres above the box top searched for returns of an object continuing upward.
ABOVE_REACH = 1.5
#: Metres of the shell around the box's sides searched for returns spilling out of it.
SHELL = 0.6
#: Metres beyond the box's sides that still count as in it: a detector's box is tight, and a
#: car's near face lies on its boundary, half its returns a hair outside.
FACE_MARGIN = 0.1


def _group_extent(values: np.ndarray, box: np.ndarray, n: int) -> np.ndarray:
    """Per box, max - min of ``values`` of its pairs (``box`` ascending; 0 for no pair)."""
    out = np.zeros(n)
    if not len(values):
        return out
    count = np.bincount(box, minlength=n)
    starts = np.r_[0, np.cumsum(count)[:-1]]
    has = count > 0
    out[has] = np.maximum.reduceat(values, starts[has]) - np.minimum.reduceat(values, starts[has])
    return out


def half_all(boxes: Boxes) -> np.ndarray:
    """Half sizes of the boxes."""
    return boxes.size / 2.0


def _depth_share(lx, ly, lz, box: np.ndarray, boxes: Boxes, n: int) -> np.ndarray:
    """Per box, how deep behind the box's near surface its body returns lie, as a share of the
    box's depth along each return's ray (0: at the surface where the ray enters the box, 1: at
    its far side), averaged with one prior return at 0.5 (no return: 0.5, undecided). A car
    fills its box: the rays stop at its faces. A pole, a pedestrian or a bollard in a car box
    stops them deep inside; a box shifted off its car holds the car's returns at its back."""
    out = np.full(n, 0.5)
    if not len(box):
        return out
    cos, sin = np.cos(boxes.yaw), np.sin(boxes.yaw)
    cx, cy, cz = boxes.center.T
    origin = np.stack(to_box_local(0.0, 0.0, 0.0, cx, cy, cz, cos, sin), axis=1)[box]
    half = half_all(boxes)[box]
    half[:, :2] += FACE_MARGIN
    lo, hi = -half.copy(), half.copy()
    lo[:, 2] += EVIDENCE_GROUND
    d = np.stack([lx, ly, lz], axis=1).astype(np.float64) - origin  # the ray, sensor to return (t = 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        t0, t1 = (lo - origin) / d, (hi - origin) / d
    near = np.nan_to_num(np.minimum(t0, t1), nan=-np.inf).max(axis=1)
    far = np.nan_to_num(np.maximum(t0, t1), nan=np.inf).min(axis=1)
    share = np.clip((1.0 - near) / np.maximum(far - near, 1e-9), 0.0, 1.0)
    total = np.bincount(box, weights=share, minlength=n)
    count = np.bincount(box, minlength=n)
    return (total + 0.5) / (count + 1.0)


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


def profile_terms(points: np.ndarray, boxes: Boxes, sensor: SensorModel) -> dict[str, np.ndarray]:
    """``above``, ``fill``, ``spill`` and ``overlap`` of every box (module docstring), plus the
    raw counts behind them (``n_body``, ``n_above``, ``n_shell``)."""
    n = len(boxes)
    if n == 0:
        zero = np.zeros(0)
        return {k: zero for k in (*PROFILE_TERMS, "n_body", "n_above", "n_shell")}
    centre, size = boxes.center.copy(), boxes.size.copy()
    size[:, :2] += 2 * SHELL
    size[:, 2] += ABOVE_REACH
    centre[:, 2] += ABOVE_REACH / 2
    grown = Boxes(centre, size, boxes.yaw)
    pair_point, starts, (lx, ly, lz) = BoxCandidates(points, grown).pairs(local=True)
    box = np.repeat(np.arange(n), np.diff(starts))
    half = boxes.size[box] / 2
    half[:, :2] += FACE_MARGIN
    z = lz.astype(np.float64) + ABOVE_REACH / 2  # height in the original box's frame
    over = (np.abs(lx) <= half[:, 0]) & (np.abs(ly) <= half[:, 1])
    body_z = (z >= -half[:, 2] + EVIDENCE_GROUND) & (z <= half[:, 2])
    body, above, shell = over & body_z, over & (z > half[:, 2]), ~over & body_z
    n_body = np.bincount(box[body], minlength=n).astype(np.float64)
    n_above = np.bincount(box[above], minlength=n).astype(np.float64)
    n_shell = np.bincount(box[shell], minlength=n).astype(np.float64)
    # azimuth span of the body returns, relative to the box centre's azimuth (no wrap at +-pi)
    pts = np.asarray(points)[pair_point[body]]
    centre_az = np.arctan2(boxes.center[:, 1], boxes.center[:, 0])
    rel = np.angle(np.exp(1j * (np.arctan2(pts[:, 1], pts[:, 0]).astype(np.float64) - centre_az[box[body]])))
    span = _group_extent(rel, box[body], n)
    az_lo, az_hi, *_ = angular_window(boxes)
    step = np.deg2rad(sensor.azimuth_resolution_deg)
    fill = np.where(n_body > 0, np.clip((span + step) / (az_hi - az_lo + step), 0.0, 1.0), 0.0)
    depth = _depth_share(lx[body], ly[body], z[body], box[body], boxes, n)
    top = np.zeros(n)
    if body.any():
        b = box[body]
        count = np.bincount(b, minlength=n)
        has = count > 0
        first = np.r_[0, np.cumsum(count)[:-1]][has]
        top[has] = (np.maximum.reduceat(z[body], first) + half_all(boxes)[has, 2]) / boxes.size[has, 2]
    return {
        "above": n_above / (n_above + n_body + 1.0),
        "depth": depth,
        "top": top,
        "fill": fill,
        "spill": np.log((n_shell + 1.0) / (n_body + 1.0)),
        "overlap": covered_share(boxes),
        "n_body": n_body, "n_above": n_above, "n_shell": n_shell,
    }
