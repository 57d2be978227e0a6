"""Cross-sensor checks of the detection filter on labelled scans without a detector.

``pcc eval detections --nuscenes ROOT`` (:func:`nuscenes_check`): a real sweep of another
sensor than the one the filter was calibrated on, judged the way held-out sweeps of sensors we
do not have will be judged. There is no detector, so the detections are constructed from the
annotations, every one with the same score (``--score``; the score term then cannot separate
anything, and the check shows whether it can reject real cars on its own):

* **true**: a box on every annotated car (``Car`` / ``Van`` labels), the annotation itself;
* **false, non-vehicle**: a car-sized box (:data:`CAR_SIZE`, nuScenes' mean car) on every
  annotated non-vehicle object (pedestrians, barriers, cones, bicycles, pushable objects, ...),
  centred on it, standing on its bottom, with its yaw: what a detector confusing that object for
  a car would output;
* **false, free ground**: ``--ground-boxes`` car boxes (seeded) standing on sampled ground
  returns 5-50 m away, overlapping no annotated object of any class.

A detector never emits two car boxes that overlap above its NMS IoU; the constructed boxes
get the same rule (:func:`nms_keep`, :data:`NMS_IOU` = 0.2 in bird's-eye view, the NMS of the
common nuScenes detectors, e.g. CenterPoint and OpenPCDet's nuScenes configs): in the order
above (cars first: an annotated car is never suppressed), a false box overlapping a kept box
above ``nms_iou`` is dropped, as the detector's NMS would drop it, and counted per group
(``suppressed_by_nms``). Without it, car boxes on neighbouring non-vehicles (a group of
pedestrians, a row of cones) overlap as no detector's output does, and the ``overlap`` term
is credited for the check's own duplicates. Boxes overlapping below the NMS IoU stay, as a
detector's do; ``--nms-iou 1`` keeps every box (the figure without the rule).

Trucks, buses, trailers and construction vehicles are neither (a car box on a truck is neither
clearly right nor clearly wrong). The filter runs through the node's own pipeline; the report
gives its operating curve (false removed vs true lost) against the points-in-box count, the
removal per group at the configured threshold, and whether each car with at least 20 returns
was kept. SynthCars runs (``--kitti`` over a SynthCars root whose detections carry ``.kind``
files) get the same per-group table by false-positive kind (:func:`pcc_ros.workflows.detection_eval.compare`).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from pcc_ros.errors import DataError
from pcc_ros.geometry.boxes import iou_bev, points_in_boxes
from pcc_ros.pipeline.filter import false_probability, local_ground
from pcc_ros.plotting import operating_curves
from pcc_ros.types import Boxes
from pcc_ros.workflows.detection_eval import (
    compare,
    print_groups,
    print_threshold_in_force,
    threshold_in_force_json,
)

log = logging.getLogger(__name__)

#: A car box on a non-vehicle: nuScenes' mean car (length, width, height; metres).
CAR_SIZE = (4.63, 1.95, 1.74)
#: Labels of the annotated objects that are not vehicles (nuScenes categories through
#: :data:`pcc_ros.data.nuscenes.CATEGORY_TO_LABEL`): people, two-wheelers, movable and static objects.
NON_VEHICLE_LABELS = ("Pedestrian", "Cyclist", "Motorcyclist", "Misc")
TRUE_LABELS = ("Car", "Van")
#: Cars with at least this many returns must be kept (the check's hard requirement).
WELL_SEEN = 20
#: BEV IoU above which a detector's NMS keeps only one of two car boxes (:func:`nms_keep`).
NMS_IOU = 0.2


def nms_keep(boxes: Boxes, protected: np.ndarray, nms_iou: float = NMS_IOU) -> np.ndarray:
    """Indices of ``boxes`` a detector's NMS would emit: greedily in the given order, a box is
    kept unless its BEV IoU with a kept box exceeds ``nms_iou``; ``protected`` boxes (the
    annotated cars) are always kept. ``nms_iou`` >= 1 keeps every box."""
    n = len(boxes)
    if n < 2 or nms_iou >= 1.0:
        return np.arange(n)
    iou = iou_bev(boxes, boxes)
    kept = np.zeros(n, dtype=bool)
    for i in range(n):  # a hundred boxes per frame: a loop over boxes, not points
        kept[i] = bool(protected[i]) or not (iou[i, kept] > nms_iou).any()
    return np.flatnonzero(kept)


def constructed_boxes(points: np.ndarray, gt: Boxes, categories: np.ndarray, score: float, ground_boxes: int,
                      seed: int, nms_iou: float = NMS_IOU,
                      suppressed: dict[str, int] | None = None) -> tuple[Boxes, np.ndarray, np.ndarray]:
    """The check's detections, their group (``"car"``, the non-vehicle's category, or
    ``"free ground"``) and truth (True = a real car), after the NMS rule (:func:`nms_keep`;
    the boxes it drops are added per group to ``suppressed``). See the module docstring."""
    rng = np.random.default_rng(seed)
    labels = gt.label.astype(str)
    cars = np.flatnonzero(np.isin(labels, TRUE_LABELS))
    others = np.flatnonzero(np.isin(labels, NON_VEHICLE_LABELS))
    true = Boxes(gt.center[cars], gt.size[cars], gt.yaw[cars], ["Car"] * len(cars), np.full(len(cars), score))
    size = np.tile(CAR_SIZE, (len(others), 1))
    centre = gt.center[others].copy()
    centre[:, 2] += (size[:, 2] - gt.size[others, 2]) / 2  # same bottom as the object
    confused = Boxes(centre, size, gt.yaw[others], ["Car"] * len(others), np.full(len(others), score))
    ground = _free_ground_boxes(points, gt, ground_boxes, score, rng)
    boxes = Boxes.concatenate([true, confused, ground])
    group = np.r_[np.full(len(cars), "car", dtype=object), np.asarray(categories, dtype=object)[others],
                  np.full(len(ground), "free ground", dtype=object)]
    is_true = np.r_[np.ones(len(cars), bool), np.zeros(len(others) + len(ground), bool)]
    keep = nms_keep(boxes, is_true, nms_iou)
    if suppressed is not None:
        for g in group[np.setdiff1d(np.arange(len(boxes)), keep)]:
            suppressed[str(g)] = suppressed.get(str(g), 0) + 1
    return boxes[keep], group[keep], is_true[keep]


def _free_ground_boxes(points: np.ndarray, gt: Boxes, count: int, score: float, rng: np.random.Generator,
                       candidates: int = 400) -> Boxes:
    """``count`` car boxes standing on ground returns 5-50 m away (the local ground within
    0.15 m of the return), overlapping no annotated box; seeded."""
    if count <= 0:
        return Boxes.empty()
    r = np.linalg.norm(points[:, :2], axis=1)
    pool = np.flatnonzero((r > 5.0) & (r < 50.0))
    if not len(pool):
        raise DataError("no scan returns 5-50 m away to place free-ground boxes on")
    pick = points[rng.choice(pool, min(candidates, len(pool)), replace=False), :3].astype(np.float64)
    m = len(pick)
    size = np.tile(CAR_SIZE, (m, 1))
    yaw = rng.uniform(-np.pi, np.pi, m)
    probe = Boxes(np.c_[pick[:, :2], pick[:, 2]], size, yaw)
    ground = local_ground(points[:, :3].astype(np.float64), probe)
    ok = np.isfinite(ground) & (np.abs(pick[:, 2] - ground) < 0.15)
    centre = np.c_[pick[:, :2], np.where(np.isfinite(ground), ground, pick[:, 2]) + size[:, 2] / 2]
    boxes = Boxes(centre, size, yaw, ["Car"] * m, np.full(m, score))
    if len(gt):
        ok &= iou_bev(boxes, gt).max(axis=1) <= 0.0
    chosen: list[int] = []
    for i in np.flatnonzero(ok):  # greedy: no two ground boxes overlap (a few hundred candidates)
        if not chosen or iou_bev(boxes[[i]], boxes[chosen]).max() <= 0.0:
            chosen.append(int(i))
        if len(chosen) == count:
            break
    if len(chosen) < count:
        log.warning("placed %d of %d free-ground boxes (not enough free ground returns)", len(chosen), count)
    return boxes[np.array(chosen, dtype=np.int64)]


def judge(pipeline, points: np.ndarray, boxes: Boxes, rings: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """The pipeline's decision on ``boxes``: p_false, status, terms and the points in each box
    (``rings``: the scan's ring field, read by ``sensor: auto``'s beam model)."""
    result = pipeline.process(points, boxes, frame_id="lidar", rings=rings)
    n = len(boxes)
    counts = np.array([len(i) for i in points_in_boxes(points[:, :3], boxes)], dtype=np.int64)
    return {
        "p_false": result.filter_score if result.filter_score is not None else np.full(n, np.nan),
        "status": np.asarray(result.status, dtype=object),
        "terms": {k: np.asarray(v, dtype=np.float64) for k, v in result.filter_terms.items()},
        "points": counts,
    }


def nuscenes_check(root: str | Path, pipeline, score: float = 0.7, ground_boxes: int = 30, seed: int = 0,
                   max_lost: float = 0.02, scene: str | None = None, scores: tuple[float, ...] = (0.5, 0.7, 0.9),
                   nms_iou: float = NMS_IOU) -> dict[str, Any]:
    """Run the check on every LIDAR_TOP key frame of a nuScenes root (see the module docstring);
    ``scores``: the configured decision is also reported with every box at each of these scores;
    ``nms_iou``: the NMS rule of the constructed boxes (>= 1: none)."""
    from pcc_ros.data.nuscenes import NuScenes

    rows: dict[str, list] = {k: [] for k in ("p_false", "points", "is_true", "group", "status", "returns", "range",
                                              "box", "frame")}
    terms: dict[str, list] = {}
    frames, by_score, suppressed = [], {s: [] for s in scores}, {}
    for k, sample in enumerate(NuScenes(root).frames(scene)):
        points = np.asarray(sample.points, dtype=np.float32)
        boxes, group, is_true = constructed_boxes(points, sample.ground_truth, sample.extras["category"], score,
                                                  ground_boxes, seed + k, nms_iou, suppressed)
        rings = points[:, list(sample.fields).index("ring")] if "ring" in sample.fields else None
        judged = judge(pipeline, points, boxes, rings)
        for key, value in (("p_false", judged["p_false"]), ("points", judged["points"]), ("is_true", is_true),
                           ("group", group), ("status", judged["status"]), ("returns", judged["points"]),
                           ("range", np.linalg.norm(boxes.center[:, :2], axis=1)),
                           ("frame", np.full(len(boxes), k))):
            rows[key].append(value)
        rows["box"].append(boxes)
        for t, v in judged["terms"].items():
            terms.setdefault(t, []).append(v)
        for s in scores:
            other = Boxes(boxes.center, boxes.size, boxes.yaw, boxes.label, np.full(len(boxes), s))
            by_score[s].append(judge(pipeline, points, other, rings)["status"])
        frames.append({"sample": sample.extras["sample_token"], "points": len(points), "boxes": len(boxes),
                       "points_xy": points[:, :2], "boxes_obj": boxes, "is_true": is_true})
    if not frames:
        raise DataError(f"{root}: no LIDAR_TOP key frames")
    cat = {k: (np.concatenate(v) if k != "box" else Boxes.concatenate(v)) for k, v in rows.items()}
    result = compare(cat["p_false"], cat["points"], cat["is_true"], cat["group"], cat["status"], max_lost)
    well = cat["is_true"] & (cat["returns"] >= WELL_SEEN)
    result["well_seen_cars"] = [
        {"returns": int(n), "range_m": round(float(r), 1), "p_false": float(p), "status": str(st)}
        for n, r, p, st in zip(cat["returns"][well], cat["range"][well], cat["p_false"][well], cat["status"][well])
    ]
    result["well_seen_cars_kept"] = bool(all(c["status"] == "kept" for c in result["well_seen_cars"]))
    non_vehicle = ~cat["is_true"] & (cat["group"] != "free ground")
    rejected = cat["status"] == "rejected"
    result["configured"]["non_vehicle_removed"] = float(rejected[non_vehicle].mean()) if non_vehicle.any() else 0.0
    result["configured"]["free_ground_removed"] = (
        float(rejected[cat["group"] == "free ground"].mean()) if (cat["group"] == "free ground").any() else 0.0)
    # The check's boxes carry one score; below the NMS IoU, car-sized boxes on neighbouring
    # non-vehicles still overlap (as a detector's may), and the overlap term reads an earlier
    # box as a higher-scored duplicate. The decision as if no box covered another (the term read
    # as 0 by the weighted sum and the trees alike), reported beside it:
    cat_terms = {t: np.concatenate(v) for t, v in terms.items()}
    cfg = pipeline.config.filter
    in_force = pipeline.threshold_in_force or (pipeline.beam_model.preset, cfg.reject_threshold)
    if "overlap" in cfg.weighted_terms and "overlap" in cat_terms:
        alone = false_probability({**cat_terms, "overlap": np.zeros(len(cat["is_true"]))}, cfg) > in_force[1]
        covered = cat_terms["overlap"] > 0
        result["configured"]["non_vehicle_removed_without_overlap"] = (
            float(alone[non_vehicle].mean()) if non_vehicle.any() else 0.0)
        result["configured"]["non_vehicle_overlapping_another"] = int((covered & non_vehicle).sum())
    result["by_score"] = {}
    for s, statuses in by_score.items():
        st = np.concatenate(statuses) == "rejected"
        result["by_score"][f"{s:g}"] = {"true_lost": float(st[cat["is_true"]].mean()),
                                         "false_removed": float(st[~cat["is_true"]].mean())}
    result.update({"nms_iou": nms_iou, "suppressed_by_nms": suppressed})
    result.update({"root": str(root), "frames": len(frames), "score": score, "ground_boxes": ground_boxes,
                   "seed": seed, "max_lost": max_lost,
                   "filter_config": {k: getattr(pipeline.config.filter, k)
                                     for k in pipeline.config.filter.__dataclass_fields__},
                   "threshold_in_force": threshold_in_force_json(in_force),
                   "_terms": cat_terms, "_rows": cat, "_frames": frames})
    return result




def print_check(result: dict[str, Any]) -> None:
    """The check's tables (Markdown) on stdout."""
    conf = result["configured"]
    print(f"\n{result['root']}: {result['frames']} frame(s), {result['true']} true car boxes, {result['false']} "
          f"false (non-vehicles + {result['ground_boxes']} free ground per frame), every score {result['score']:g}")
    nms = result.get("suppressed_by_nms") or {}
    print(f"NMS rule (BEV IoU > {result.get('nms_iou', NMS_IOU):g}): false boxes a detector would not emit, "
          f"dropped: {sum(nms.values())}" + (f" ({', '.join(f'{g}: {n}' for g, n in sorted(nms.items()))})" if nms
                                            else ""))
    print_groups(result, "false group")
    print(f"non-vehicle boxes removed at the configured threshold: {conf['non_vehicle_removed']:.1%}; "
          f"free ground: {conf['free_ground_removed']:.1%}; unjudged: {conf['unjudged']}")
    print_threshold_in_force(result.get("threshold_in_force"))
    if "non_vehicle_removed_without_overlap" in conf:
        print(f"non-vehicle boxes partly covered by an earlier box of the check (below the NMS IoU): "
              f"{conf['non_vehicle_overlapping_another']}; removed without the overlap term: "
              f"{conf['non_vehicle_removed_without_overlap']:.1%}")
    for car in result["well_seen_cars"]:
        print(f"car with {car['returns']} returns at {car['range_m']} m: p_false {car['p_false']:.3f}, {car['status']}")
    print("configured decision with every box at score s: "
          + "; ".join(f"s={s}: {v['true_lost']:.1%} true lost, {v['false_removed']:.1%} false removed"
                      for s, v in result["by_score"].items()))


def plot_check(result: dict[str, Any], path: Path, title: str) -> None:
    """PNG: operating curves (filter vs points-in-box), p_false by group, BEV of the first frame
    with every box coloured by truth and decision."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from pcc_ros.geometry.boxes import box_corners

    rows = result["_rows"]
    fig, axes = plt.subplots(1, 3, figsize=(18, 5.8))
    ax = axes[0]
    conf = result["configured"]
    operating_curves(ax, {name: method["curve"] for name, method in result["methods"].items()},
                     (conf["true_lost"], conf["false_removed"]), result["max_lost"], "true car boxes", "false boxes",
                     (-2, 102))
    ax.set_ylim(-2, 102)
    ax = axes[1]
    p = rows["p_false"]
    broad = np.where(rows["is_true"], "car", np.where(rows["group"] == "free ground", "free ground", "non-vehicle"))
    bins = np.linspace(0, 1, 26)
    for g in ("car", "non-vehicle", "free ground"):
        sel = (broad == g) & np.isfinite(p)
        ax.hist(p[sel], bins=bins, alpha=0.55, label=f"{g} ({int(sel.sum())})")
    ax.axvline(result["threshold_in_force"]["threshold"], color="k", ls="--", lw=1, label="reject threshold in force")
    ax.set_xlabel("p_false")
    ax.set_title("filter probability by group")
    ax.legend(fontsize=8)
    ax = axes[2]
    first = result["_frames"][0]
    xy = first["points_xy"]
    near = np.abs(xy).max(axis=1) < 60
    ax.scatter(xy[near, 0], xy[near, 1], s=0.2, c="0.6")
    sel = rows["frame"] == 0
    boxes = rows["box"][np.flatnonzero(sel)]
    corners = box_corners(boxes)[:, [0, 1, 2, 3, 0], :2] if len(boxes) else np.zeros((0, 5, 2))
    colour = {(True, "kept"): "tab:green", (True, "rejected"): "tab:red", (False, "rejected"): "tab:blue",
              (False, "kept"): "tab:orange"}
    for c, t, st in zip(corners, rows["is_true"][sel], rows["status"][sel]):
        ax.plot(c[:, 0], c[:, 1], color=colour.get((bool(t), str(st)), "k"), lw=1)
    for (t, st), col in colour.items():
        ax.plot([], [], color=col, label=f"{'car' if t else 'false'} {st}")
    ax.plot([], [], color="k", label="unjudged")
    ax.set_aspect("equal")
    ax.set_xlim(-60, 60)
    ax.set_ylim(-60, 60)
    ax.set_title("frame 0 (BEV, metres)")
    ax.legend(fontsize=8, loc="lower left")
    fig.suptitle(title)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=80)
    plt.close(fig)


def check_json(result: dict[str, Any]) -> dict[str, Any]:
    """The result without the arrays kept for the plot (curves included)."""
    return {k: v for k, v in result.items() if not k.startswith("_")}
