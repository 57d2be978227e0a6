"""Real-data completion metrics: what a completion of a real scan can be scored on without a
complete shape (``pcc eval --real``).

Per instance, all in metres (sensor frame; canonical values times the box length):

* ``completeness``: mean distance from each point of the track's *aggregated partial ground
  truth* (every frame's crop of the car, motion-compensated by its box and voxel-thinned,
  see :mod:`pcc_ros.data.track_aggregate`) to the nearest completion point. Lower = more of
  what the car really looked like over the sequence is covered (the AML / TraPCC KITTI
  protocol's coverage direction).
* ``fidelity``: mean distance (MCD, not squared) from each *input* point to the nearest
  completion point: does the completion keep what was observed?
* ``fidelity_generated``: the same against only the completion points that are not copies of
  input points (a backend that returns the input plus new points scores 0 on ``fidelity``
  trivially; this shows whether the *new* points lie on the observed surface).
* ``spacing``: the input's own sampling spacing, mean distance from each input point to its
  nearest other input point. Fidelity within ~2x spacing means "as close as the scan itself".
* ``side_cd``: TraPCC L-S, squared Chamfer of the side-view (x-z) projections against the
  aggregated reference, m^2.
* ``inside_box``: share of completion points inside the labelled box (+ ``BOX_TOLERANCE_M``).
* ``bottom_gap`` / ``top_gap``: box bottom to the completion's 1st z-percentile and the
  completion's 99th z-percentile to the box top (positive = floating above the bottom /
  short of the top).
* ``lateral_offset``: |mean y| of the completion, the *lateral balance* (the front view's left /
  right balance; a completion that fills only the observed side is lopsided; 0 for a symmetric car).
* ``far_completeness``: ``completeness`` restricted to the reference's points in the box half away
  from the sensor (the unseen half, :func:`~pcc_ros.metrics.balance.far_completeness`; NaN when the
  reference has none there).
* ``completeness_sym`` / ``far_completeness_sym``: the same two against the *symmetric
  reference*, the aggregated partial GT united with its reflection about the box's x-z plane
  (:func:`symmetric_reference`). Cars are left / right symmetric, so where a track was seen
  from one flank only (a car passed on one side), the mirrored points stand for the flank the
  sensor never saw, and a completion that fills it is not scored as if it had invented points;
  the plain reference stays the primary one (it holds only measured points).
* ``consistency``: symmetric Chamfer-L1 between the completions of the same track in consecutive
  frames, box frame (:func:`~pcc_ros.metrics.balance.track_consistency`); filled in by the
  evaluation, which knows the tracks (NaN for a track's first frame).
* ``points``: output points, to see whether a 5-point and a 4000-point input get the same.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from pcc_ros.geometry.canonical import mirror_y
from pcc_ros.metrics.balance import far_completeness, lateral_offset
from pcc_ros.metrics.chamfer import nearest_distances
from pcc_ros.metrics.gtfree import side_view_cd

#: Slack around the box for ``inside_box`` (labels are tight; KITTI boxes are ~cm accurate).
BOX_TOLERANCE_M = 0.05
#: Distance under which a completion point counts as a copy of an input point (canonical).
COPY_TOLERANCE = 1e-6

#: metric -> (unit, lower is better, one-line meaning); table order.
REAL_METRICS: dict[str, tuple[str, bool | None, str]] = {
    "completeness": ("m", True, "aggregated partial GT -> completion, mean NN distance"),
    "fidelity": ("m", True, "input -> completion, mean NN distance (MCD)"),
    "fidelity_generated": ("m", True, "input -> completion points that are not input copies, MCD"),
    "spacing": ("m", None, "input -> nearest other input point, mean (the scan's own sampling)"),
    "side_cd": ("m^2", True, "TraPCC L-S: squared Chamfer of side-view (x-z) projections vs aggregated GT"),
    "inside_box": ("-", False, f"share of completion points inside the box (+{BOX_TOLERANCE_M} m)"),
    "bottom_gap": ("m", True, "box bottom -> 1st percentile of completion z (positive: floating)"),
    "top_gap": ("m", True, "99th percentile of completion z -> box top (positive: short of the top)"),
    "lateral_offset": ("m", True, "lateral balance: |mean y| of the completion (front-view left/right balance)"),
    "far_completeness": ("m", True, "aggregated GT's points in the box half away from the sensor -> completion"),
    "completeness_sym": ("m", True, "aggregated GT united with its left/right reflection -> completion"),
    "far_completeness_sym": ("m", True, "the symmetric reference's points in the unseen half -> completion"),
    "consistency": ("m", True, "symmetric Chamfer-L1 between a track's completions in consecutive frames"),
    "points": ("count", None, "output points per instance"),
}


def input_spacing(partial: np.ndarray) -> float:
    """Mean distance from each point to its nearest *other* point (NaN for < 2 points)."""
    pts = np.asarray(partial, dtype=np.float64)
    if len(pts) < 2:
        return float("nan")
    d, _ = cKDTree(pts).query(pts, k=2)
    return float(d[:, 1].mean())


def symmetric_reference(reference: np.ndarray) -> np.ndarray:
    """The aggregated partial GT united with its reflection ``y -> -y`` (canonical box frame).

    Not re-thinned: each point and its reflection count once, so a flank seen only from one
    side weighs as much as the seen one, and where both flanks were seen both are doubled alike."""
    ref = np.asarray(reference, dtype=np.float64).reshape(-1, 3)
    return np.concatenate([ref, mirror_y(ref)])


def real_instance_metrics(
    completion: np.ndarray, partial: np.ndarray, reference: np.ndarray, box_size: np.ndarray,
    origin: np.ndarray | None = None,
) -> dict[str, float]:
    """Every per-instance real-data metric of one instance (canonical clouds in, metres out).

    ``origin``: the sensor in the canonical frame, which says which half is unseen
    (``far_completeness`` is NaN without it). ``consistency`` spans two frames: NaN here."""
    size = np.asarray(box_size, dtype=np.float64)
    length = float(size[0])
    comp = np.asarray(completion, dtype=np.float64).reshape(-1, 3)
    part = np.asarray(partial, dtype=np.float64).reshape(-1, 3)
    out: dict[str, float] = {"points": float(len(comp))}
    if len(comp) == 0:
        nan = float("nan")
        out.update({k: nan for k in REAL_METRICS if k != "points"})
        out["inside_box"] = 0.0
        return out
    out["consistency"] = float("nan")
    out["completeness"] = float(nearest_distances(reference, comp).mean()) * length
    out["far_completeness"] = (far_completeness(reference, comp, origin) * length if origin is not None
                               else float("nan"))
    sym = symmetric_reference(reference)
    out["completeness_sym"] = float(nearest_distances(sym, comp).mean()) * length
    out["far_completeness_sym"] = (far_completeness(sym, comp, origin) * length if origin is not None
                                   else float("nan"))
    out["fidelity"] = float(nearest_distances(part, comp).mean()) * length
    copies = nearest_distances(comp, part) <= COPY_TOLERANCE
    generated = comp[~copies]
    out["fidelity_generated"] = (
        float(nearest_distances(part, generated).mean()) * length if len(generated) else float("nan")
    )
    out["spacing"] = input_spacing(part) * length
    out["side_cd"] = side_view_cd(comp, reference) * length**2
    half = size / length / 2.0
    tol = BOX_TOLERANCE_M / length
    out["inside_box"] = float(np.all(np.abs(comp) <= half + tol, axis=1).mean())
    lo, hi = np.percentile(comp[:, 2], [1.0, 99.0])
    out["bottom_gap"] = float(lo + half[2]) * length
    out["top_gap"] = float(half[2] - hi) * length
    out["lateral_offset"] = lateral_offset(comp) * length
    return out


def mean_rows(rows: Sequence[dict[str, float]], mask: np.ndarray) -> dict[str, Any]:
    """Per-metric means over the masked rows (NaN-aware); ``None`` for an empty band."""
    chosen = [r for r, m in zip(rows, mask) if m]
    out: dict[str, Any] = {"count": len(chosen)}
    for key in REAL_METRICS:
        values = np.array([r.get(key, np.nan) for r in chosen], dtype=np.float64)
        values = values[np.isfinite(values)]
        out[key] = float(values.mean()) if len(values) else None
    if chosen:
        pts = np.array([r["points"] for r in chosen])
        out["points_min"] = float(pts.min())
        out["points_max"] = float(pts.max())
        out["consistency_pairs"] = int(np.isfinite([r.get("consistency", np.nan) for r in chosen]).sum())
    return out


def draw_three_views(
    path: Any,
    examples: Sequence[dict[str, Any]],
    columns: Sequence[str],
    title: str,
    max_draw: int = 3000,
) -> None:
    """PNG grid of real completions: per example three rows (side x-z, front y-z, top x-y),
    one column per cloud (input, each backend, aggregated reference), the box drawn in grey.

    ``examples``: dicts with ``label`` (row text), ``box`` (canonical half extents, (3,)) and
    ``clouds`` (column name -> canonical (n, 3) cloud). Axes are metres about the box centre.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    views = (("side", 0, 2), ("front", 1, 2), ("top", 0, 1))
    axis_names = "xyz"
    rows = len(examples) * len(views)
    fig, axes = plt.subplots(rows, len(columns), figsize=(2.3 * len(columns), 1.55 * rows), squeeze=False)
    rng = np.random.default_rng(0)
    for e, ex in enumerate(examples):
        length = float(ex["length"])
        half = np.asarray(ex["box"], dtype=np.float64) * length
        for v, (vname, u, w) in enumerate(views):
            r = e * len(views) + v
            lim_u, lim_w = 0.62 * length, half[w] * 1.35
            for c, name in enumerate(columns):
                ax = axes[r, c]
                cloud = np.asarray(ex["clouds"].get(name, np.zeros((0, 3))), dtype=np.float64) * length
                if len(cloud) > max_draw:
                    cloud = cloud[rng.choice(len(cloud), max_draw, replace=False)]
                colour = "tab:red" if c == 0 else ("tab:green" if c == len(columns) - 1 else "tab:blue")
                ax.scatter(cloud[:, u], cloud[:, w], s=0.6, c=colour, linewidths=0)
                ax.add_patch(plt.Rectangle((-half[u], -half[w]), 2 * half[u], 2 * half[w], fill=False,
                                           ec="0.6", lw=0.6))
                ax.set_xlim(-max(lim_u, half[u] * 1.15), max(lim_u, half[u] * 1.15))
                ax.set_ylim(-lim_w, lim_w)
                ax.set_aspect("equal")
                ax.set_xticks([])
                ax.set_yticks([])
                if r == 0:
                    ax.set_title(name, fontsize=8)
                if c == 0:
                    ax.set_ylabel(f"{vname} ({axis_names[u]}-{axis_names[w]})", fontsize=7)
                if c == 0 and v == 0:
                    ax.text(0.01, 0.99, ex["label"], transform=ax.transAxes, fontsize=6, va="top")
                if v == 0:
                    ax.text(0.99, 0.01, f"{len(ex['clouds'].get(name, ()))} pts", transform=ax.transAxes,
                            fontsize=6, ha="right", va="bottom")
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
