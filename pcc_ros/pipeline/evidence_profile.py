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
* ``corner``: the share of the returns up to 70 % of the box height that lie in its four vertical
  corner columns (:data:`CORNER_COLUMNS`). A car's body fills its box to the corners; a vegetation
  blob or a bush (an ellipsoid) leaves them air, a bin or a low wall inside the box keeps off them.

All are dimensionless and read the scan geometry only through the sensor's azimuth step
(the beam model's), so one weight set serves every sensor. The boxes grown by the shell and
the reach above are a query of the scan's BEV index (:mod:`pcc_ros.pipeline.evidence_index`; in
the pipeline the local ground's, sorted once for both), then one compiled loop tests each
candidate pair and uses it in the same visit (:mod:`pcc_ros.pipeline.profile_kernels`).
"""

from __future__ import annotations

from collections.abc import Collection

import numpy as np

from pcc_ros.geometry.beams import SensorModel
from pcc_ros.geometry.boxes import circles_meet, iou_bev_pairs, round_down_to, round_up_to
from pcc_ros.geometry.canonical import to_box_local
from pcc_ros.pipeline.evidence import EVIDENCE_GROUND, angular_window, evidence
from pcc_ros.pipeline.evidence_index import BevIndex, Footprints
from pcc_ros.scratch import Scratch
from pcc_ros.types import Boxes

#: The profile terms, in the order :func:`profile_terms` returns them.
PROFILE_TERMS = ("above", "fill", "spill", "overlap", "depth", "top", "corner")
#: What each term measures (the node's parameter descriptions of their weights).
PROFILE_TERM_DOCS = {
    "above": "the share of the returns over the box footprint that lie above its top (up to 1.5 m over it)",
    "fill": "the share of the box's azimuth span its returns cover",
    "spill": "log((returns in a 0.6 m shell around the box's sides + 1) / (returns in the box + 1))",
    "overlap": "the largest share of the box footprint a higher-scored box covers",
    "depth": "how deep behind the box's near surface its returns lie (share of its depth along each ray)",
    "top": "the highest in-box return's height as a share of the box height",
    "corner": "the share of the returns up to 70 % of the box height lying in its four corner columns (with "
              "prior returns at a car's value)",
}
#: Metres above the box top searched for returns of an object continuing upward.
ABOVE_REACH = 1.5
#: Metres of the shell around the box's sides searched for returns spilling out of it.
SHELL = 0.6
#: Metres beyond the box's sides that still count as in it: a detector's box is tight, and a
#: car's near face lies on its boundary, half its returns a hair outside.
FACE_MARGIN = 0.1
#: ``depth`` of a car: the median share of a true car box's depth at which its returns lie
#: (0.19-0.23 on every simulated sensor, docs/filter.md), and the number of such prior returns
#: ``depth`` starts from. A box with a handful of returns (far, occluded) keeps a car's value
#: until its own returns say otherwise: a few deep returns are noise, dozens are an object
#: smaller than the box. The strength was chosen by leave-one-sensor-out cross-validation on
#: the calibration sensors (1, 10, 20, 40 tried: 20-40 best, 1 worst).
DEPTH_PRIOR = 0.2
DEPTH_PRIOR_RETURNS = 20.0
#: ``above``: prior returns at body height (none above the top), for the same reason.
ABOVE_PRIOR_RETURNS = 10.0
#: ``corner``: the box's four vertical corner columns, as shares of its length and width (the outer
#: 20 % of the length at each end by the outer 30 % of the width at each side), and the top of the
#: height band whose returns it counts (70 % of the box height: below the windows, where a car's
#: body is widest; the bottom is the body's, :data:`EVIDENCE_GROUND` over the box bottom). A car's
#: body fills its box to the corners (bumpers, wings); an ellipsoid (a vegetation blob, a bush)
#: leaves them air, a bin or a low wall standing in a car-sized box keeps off them.
CORNER_COLUMNS = (0.2, 0.3, 0.7)
#: ``corner`` of a car: the median share on the true car boxes of the seed-11 calibration sets
#: (0.44-0.46 on every simulated sensor), and the number of such prior returns it starts from: a
#: box of a handful of returns keeps a car's value.
CORNER_PRIOR = 0.45
CORNER_PRIOR_RETURNS = 10.0


def covered_share(boxes: Boxes) -> np.ndarray:
    """Per box, the largest share of its BEV footprint that a box with a higher score (ties:
    an earlier box) covers: the duplicate check an NMS would make, measured, not applied."""
    n = len(boxes)
    share = np.zeros(n)
    if n < 2:
        return share
    score = np.nan_to_num(np.asarray(boxes.score, dtype=np.float64), nan=-np.inf)
    idx = np.arange(n)
    better = (score[None, :] > score[:, None]) | ((score[None, :] == score[:, None]) & (idx[None, :] < idx[:, None]))
    i, j = np.nonzero(better & circles_meet(boxes, boxes))  # only these pairs can cover anything
    if len(i):
        iou = iou_bev_pairs(boxes, i, j)
        area = boxes.size[:, 0] * boxes.size[:, 1]
        # intersection from IoU: I = IoU * (A_i + A_j) / (1 + IoU)
        inter = iou * (area[i] + area[j]) / (1.0 + iou)
        np.maximum.at(share, i, inter / np.maximum(area[i], 1e-12))
    return np.clip(share, 0.0, 1.0)


def profile_terms(points: np.ndarray, boxes: Boxes, sensor: SensorModel,
                  measure: Collection[str] | None = None) -> dict[str, np.ndarray]:
    """``above``, ``fill``, ``spill``, ``overlap``, ``depth``, ``top`` and ``corner`` of every box (module
    docstring), plus the raw counts behind them (``n_body``, ``n_above``, ``n_shell``).

    ``depth``: how deep behind the box's near surface its body returns lie, as a share of the
    box's depth along each return's ray (0: where the ray enters the box, 1: its far side),
    averaged with :data:`DEPTH_PRIOR_RETURNS` prior returns at a car's :data:`DEPTH_PRIOR` (no
    return: a car's value; the term then says nothing and the others judge). A car fills its
    box: the rays stop at its faces; a pole, a pedestrian or a bollard in a car box stops them
    deep inside; a box shifted off its car holds the car's returns at its back. ``above``
    counts :data:`ABOVE_PRIOR_RETURNS` prior body returns. ``top``: the highest
    body return over the box bottom, as a share of the box height (0 without one).

    ``measure``: the terms wanted (default all); only they are returned, with the same values.
    ``overlap`` alone needs no pass over the scan; without ``spill`` the boxes grow sideways by
    the face margin only, not by the shell (about half the candidate pairs of a car box)."""
    wanted = set(PROFILE_TERMS if measure is None else measure) & set(PROFILE_TERMS)
    if not wanted - {"overlap"} or not len(boxes):  # no pass over the scan
        return terms_before_pass(boxes, wanted)[0]
    return evidence(points, boxes, sensor, rays=False, expected=False, ground=False, profile=wanted).profile


class ProfileQuery:
    """A profile pass's boxes (:func:`grown_boxes`) as the scan's index sees them
    (:attr:`footprints`), their exact test's values in the scan's precision, and the
    measurement over the index (:meth:`measure`)."""

    def __init__(self, boxes: Boxes, wanted: set[str], dt: type) -> None:
        grown = grown_boxes(boxes, "spill" in wanted)
        if not grown.valid_mask().all():
            grown.validate()  # DataError naming the box
        self.boxes, self.wanted, self.dt = boxes, wanted, dt
        half = grown.size / 2.0
        # the test of BoxCandidates (margin 0): z bounds rounded outward to the scan's precision
        zlo = round_up_to(grown.center[:, 2] - half[:, 2], dt)
        zhi = round_down_to(grown.center[:, 2] + half[:, 2], dt)
        cos, sin = np.cos(grown.yaw), np.sin(grown.yaw)
        self.test = np.stack([zlo, zhi, grown.center[:, 0], grown.center[:, 1], cos, sin, half[:, 0], half[:, 1]],
                             axis=1).astype(dt)
        self.cz = grown.center[:, 2].astype(dt)
        self.footprints = Footprints(grown.center[:, 0], grown.center[:, 1], cos, sin, half[:, 0], half[:, 1],
                                     float(zlo.min()), float(zhi.max()))

    def measure(self, x: np.ndarray, y: np.ndarray, z: np.ndarray, index: BevIndex | None, runs, sensor: SensorModel,
                ws: Scratch) -> dict[str, np.ndarray]:
        """The pass-measured terms (and raw counts) from the candidates of the boxes' cell
        ``runs`` in ``index`` (``None``: an empty scan, no candidate); ``ws``: the calling
        thread's work arrays."""
        from pcc_ros.pipeline import profile_kernels as kernels  # numba: heavy, only when measuring

        boxes, wanted = self.boxes, self.wanted
        origin, centre_az = box_frames(boxes)
        out = np.zeros((len(boxes), 9))
        if index is not None:
            marks = ws("profile_marks", (len(x) >> 6) + 1, np.uint64)
            marks[:] = 0  # a bit per point (15 kB for 120k points)
            kernels.profile_cells(x, y, z, index.order, index.start, *runs, self.test, self.cz,
                                  np.ascontiguousarray(boxes.size / 2), origin, centre_az, ABOVE_REACH / 2,
                                  FACE_MARGIN, EVIDENCE_GROUND, "fill" in wanted,
                                  np.array(CORNER_COLUMNS if "corner" in wanted else (), dtype=np.float64), out,
                                  ws("profile_share", len(x), np.float64), marks)
        return terms_from_counts(out, boxes, sensor, wanted)


def terms_before_pass(boxes: Boxes, wanted: set[str]) -> tuple[dict[str, np.ndarray], bool]:
    """The terms that need no pass over the scan (``overlap``; every term of an empty frame) and
    whether a pass is still needed for the rest of ``wanted``."""
    if len(boxes) == 0:
        zero = np.zeros(0)
        return {k: zero for k in (*sorted(wanted), "n_body", "n_above", "n_shell")}, False
    out_terms = {"overlap": covered_share(boxes)} if "overlap" in wanted else {}
    return out_terms, bool(wanted - {"overlap"})


def grown_boxes(boxes: Boxes, spill: bool) -> Boxes:
    """The boxes a profile pass gathers candidate returns in: grown sideways by the face margin
    (and the shell when ``spill`` is measured) and upwards by :data:`ABOVE_REACH`."""
    centre, size = boxes.center.copy(), boxes.size.copy()
    # (without the shell, a 5 cm slack past the face margin: the kernel's body test of a point
    # on that boundary must never depend on the rounding of the grown box's half size)
    size[:, :2] += 2 * ((SHELL if spill else 0.05) + FACE_MARGIN)
    size[:, 2] += ABOVE_REACH
    centre[:, 2] += ABOVE_REACH / 2
    return Boxes(centre, size, boxes.yaw)


def box_frames(boxes: Boxes) -> tuple[np.ndarray, np.ndarray]:
    """Per box, the sensor origin in the box's frame ``(n, 3)`` and the azimuth of its centre:
    what a pass needs to measure each return's depth along its ray and its azimuth."""
    cos, sin = np.cos(boxes.yaw), np.sin(boxes.yaw)
    cx, cy, cz = boxes.center.T
    origin = np.ascontiguousarray(np.stack(to_box_local(0.0, 0.0, 0.0, cx, cy, cz, cos, sin), axis=1))
    return origin, np.arctan2(cy, cx)


def terms_from_counts(out: np.ndarray, boxes: Boxes, sensor: SensorModel, wanted: set[str]) -> dict[str, np.ndarray]:
    """The pass-measured terms of ``wanted`` from a pass's per-box counts (the columns of
    :func:`pcc_ros.pipeline.profile_kernels.profile_cells`), with the raw counts behind them
    (``n_shell`` only when ``spill`` is wanted)."""
    from pcc_ros.pipeline import profile_kernels as col  # the pass's column layout

    n_body, n_above, n_shell = out[:, col.BODY], out[:, col.ABOVE], out[:, col.SHELL]
    has = n_body > 0
    terms: dict[str, np.ndarray] = {}
    if "fill" in wanted:
        az_lo, az_hi, *_ = angular_window(boxes)
        step = np.deg2rad(sensor.azimuth_resolution_deg)
        span = out[:, col.AZ_MAX] - out[:, col.AZ_MIN]
        terms["fill"] = np.where(has, np.clip((span + step) / (az_hi - az_lo + step), 0.0, 1.0), 0.0)
    terms.update({
        "above": n_above / (n_above + n_body + ABOVE_PRIOR_RETURNS),
        "spill": np.log((n_shell + 1.0) / (n_body + 1.0)),
        "depth": (out[:, col.DEPTH_SUM] + DEPTH_PRIOR * DEPTH_PRIOR_RETURNS) / (n_body + DEPTH_PRIOR_RETURNS),
        "top": np.where(has, (out[:, col.TOP] + boxes.size[:, 2] / 2) / boxes.size[:, 2], 0.0),
    })
    if "corner" in wanted:
        terms["corner"] = (out[:, col.CORNER] + CORNER_PRIOR * CORNER_PRIOR_RETURNS) / (out[:, col.MID]
                                                                                      + CORNER_PRIOR_RETURNS)
    found = {k: v for k, v in terms.items() if k in wanted}
    found.update({"n_body": n_body, "n_above": n_above})
    if "spill" in wanted:
        found["n_shell"] = n_shell
    return found
