"""A simulated 3D car detector: ground truth made imperfect the way real detectors are.

True detections come from the labelled vehicles, missed more often the fewer LiDAR
points a car has (heavily occluded or far cars), with noise on centre, size and yaw
that grows with distance and sparsity, and an occasional heading flip. False positives
come in four documented kinds (:data:`FALSE_KINDS`; ``docs/synthcars.md``), each detection
labelled with its kind so an evaluation can report per kind:

* ``confusion`` — a car box on a non-vehicle object (pedestrian, pole, bollard, sign,
  bicycle, bush, tree, wall, fence, bin): each object has a fixed per-frame ``confusion``
  probability, so a bush that looks like a car keeps fooling the detector frame after frame,
  as real ones do;
* ``ghost`` — a car box on free ground or floating in empty space, 5-45 m away;
* ``far`` — a far, sparse hit: a car box 45-75 m away where a few returns (ground, a far
  object's edge) were enough for the detector;
* ``misplaced`` — a box on a real car displaced by 0.6-1.0 car lengths along it or 0.8-1.2
  widths across (BEV IoU < 0.3 with the car): in place of the car's true detection
  (misplaced) or beside it (a duplicate the detector's NMS let through).

Scores: true detections mostly high, false ones mostly lower, with overlap, so no score
threshold separates them and the filter has real work to do.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from pcc_ros.geometry.transforms import wrap_angle
from pcc_ros.types import Boxes

#: The false-positive kinds of :func:`detect` (true detections are labelled ``"true"``).
FALSE_KINDS = ("confusion", "ghost", "far", "misplaced")
KINDS = ("true", *FALSE_KINDS)


@dataclass(frozen=True)
class DetectorParams:
    """Miss, noise and false-positive model (metres, radians)."""

    half_points: float = 12.0  # visible points at which a car is detected with p = 1 - 1/e
    max_range: float = 70.0
    center_sigma: tuple[float, float] = (0.05, 0.003)  # sigma = a + b * distance
    size_sigma: float = 0.04  # relative
    yaw_sigma: float = 0.04
    flip_probability: float = 0.03
    clutter_range: float = 55.0
    clutter_min_points: int = 15
    confusion_scale: float = 1.0  # multiplies every object's confusion probability
    empty_space_rate: float = 0.6  # Poisson mean of ghosts per frame (free ground / empty space)
    floating_share: float = 0.3  # share of ghosts floating 0.4-1.5 m above the ground (empty space)
    far_rate: float = 0.4  # Poisson mean of far, sparse hits per frame
    far_range: tuple[float, float] = (45.0, 75.0)
    misplaced_probability: float = 0.03  # per true detection: displaced instead of on the car
    duplicate_probability: float = 0.04  # per true detection: a displaced second box beside it

    def to_dict(self) -> dict:
        return asdict(self)


def _car_sizes(rng: np.random.Generator, k: int) -> np.ndarray:
    return np.c_[rng.normal(4.0, 0.3, k), rng.normal(1.65, 0.08, k), rng.normal(1.5, 0.08, k)]


def _ground_boxes(points: np.ndarray, ground_z: float, rng: np.random.Generator, k: int, score: np.ndarray,
                  lift: np.ndarray) -> Boxes:
    """``k`` car boxes centred on ``points`` (rows), standing ``lift`` metres above the ground."""
    car = _car_sizes(rng, k)
    c = np.c_[points[:, :2], ground_z + car[:, 2] / 2 + lift]
    return Boxes(c, car, rng.uniform(-np.pi, np.pi, k), ["Car"] * k, score)


def displaced(boxes: Boxes, rng: np.random.Generator) -> Boxes:
    """Copies of ``boxes`` moved 0.6-1.0 lengths along or 0.8-1.2 widths across their own axis
    (BEV IoU with the original below 0.3): a misplaced or duplicated detection."""
    n = len(boxes)
    along = rng.random(n) < 0.5
    sign = np.where(rng.random(n) < 0.5, -1.0, 1.0)
    step = np.where(along, rng.uniform(0.6, 1.0, n) * boxes.size[:, 0], rng.uniform(0.8, 1.2, n) * boxes.size[:, 1])
    local = np.c_[np.where(along, step, 0.0), np.where(along, 0.0, step)] * sign[:, None]
    c, s = np.cos(boxes.yaw), np.sin(boxes.yaw)
    centre = boxes.center.copy()
    centre[:, 0] += c * local[:, 0] - s * local[:, 1]
    centre[:, 1] += s * local[:, 0] + c * local[:, 1]
    return Boxes(centre, boxes.size.copy(), boxes.yaw.copy(), ["Car"] * n, boxes.score.copy())

def detect(
    gt: Boxes,
    gt_points: np.ndarray,
    clutter: Boxes,
    clutter_points: np.ndarray,
    clutter_confusion: np.ndarray,
    ground_points: np.ndarray,
    ground_z: float,
    rng: np.random.Generator,
    params: DetectorParams | None = None,
    clutter_names: np.ndarray | None = None,
) -> tuple[Boxes, np.ndarray, np.ndarray]:
    """Detections (sensor frame), their kind (:data:`KINDS`) and the non-vehicle object each
    confusion sits on (``"-"`` for the others), sorted by score.

    Args:
        gt: labelled vehicles in the sensor frame (label Car/Van).
        gt_points: ``(N,)`` visible LiDAR returns of each vehicle.
        clutter: boxes of non-vehicle objects (bushes, walls, bins, pedestrians, furniture ...).
        clutter_points: visible returns of each non-vehicle object.
        clutter_confusion: per-frame probability that the detector fires on each of them.
        ground_points: ``(G, 3)`` visible ground returns (candidate ghosts and far hits).
        ground_z: ground height in the sensor frame (for box placement).
        clutter_names: the objects' names (``"bollard"`` ...), recorded for the confusions.
    """
    p = params or DetectorParams()
    names = np.full(len(clutter), "-", dtype=object) if clutter_names is None else np.asarray(clutter_names, object)
    dist = np.linalg.norm(gt.center[:, :2], axis=1)
    p_det = (1 - np.exp(-gt_points / p.half_points)) * np.where(dist < p.max_range, 1.0, 0.0)
    hit = rng.random(len(gt)) < p_det
    n = int(hit.sum())
    d, pts = dist[hit], gt_points[hit]
    sigma = (p.center_sigma[0] + p.center_sigma[1] * d) * (1 + 2.0 / np.sqrt(pts + 1))
    center = gt.center[hit] + rng.normal(size=(n, 3)) * sigma[:, None] * np.array([1.0, 1.0, 0.5])
    size = gt.size[hit] * np.exp(rng.normal(0, p.size_sigma, (n, 3)))
    yaw = gt.yaw[hit] + rng.normal(0, p.yaw_sigma, n) * (1 + 3.0 / np.sqrt(pts + 1))
    yaw = wrap_angle(yaw + np.pi * (rng.random(n) < p.flip_probability))
    quality = 1 - np.exp(-pts / 80.0)
    score = rng.beta(2 + 6 * quality, 1.5)
    on_cars = Boxes(center, size, yaw, gt.label[hit], score)
    # Misplaced (instead of the true box) and duplicated (beside it) boxes on real cars.
    u = rng.random(n)
    misplace = u < p.misplaced_probability
    duplicate = (u >= p.misplaced_probability) & (u < p.misplaced_probability + p.duplicate_probability)
    moved = displaced(on_cars[misplace | duplicate], rng)
    moved.score = moved.score * rng.uniform(0.6, 1.0, len(moved))
    true = on_cars[~misplace]

    # Confusions: a car-sized box on a non-vehicle object's footprint.
    cd = np.linalg.norm(clutter.center[:, :2], axis=1)
    eligible = (cd < p.clutter_range) & (clutter_points >= p.clutter_min_points)
    fire = eligible & (rng.random(len(clutter)) < np.clip(clutter_confusion * p.confusion_scale, 0, 1))
    k = int(fire.sum())
    car = _car_sizes(rng, k)
    c = clutter.center[fire].copy()
    c[:, :2] += rng.normal(0, 0.3, (k, 2))
    c[:, 2] = ground_z + car[:, 2] / 2 + rng.normal(0, 0.05, k)
    confusion = Boxes(c, car, wrap_angle(clutter.yaw[fire] + rng.normal(0, 0.3, k)), ["Car"] * k, rng.beta(2, 3.5, k))

    # Ghosts: free ground (a visible ground return) or empty space above it, 5-45 m away.
    g_range = np.linalg.norm(ground_points[:, :2], axis=1) if len(ground_points) else np.zeros(0)
    near = np.flatnonzero((g_range > 5.0) & (g_range < 45.0))
    m = min(int(rng.poisson(p.empty_space_rate)), len(near))
    lift = np.where(rng.random(m) < p.floating_share, rng.uniform(0.4, 1.5, m), 0.0)
    ghost = _ground_boxes(ground_points[rng.choice(near, m, replace=False)] if m else np.zeros((0, 3)), ground_z,
                          rng, m, rng.beta(1.6, 4.0, m), lift)

    # Far, sparse hits: 45-75 m, where a handful of returns made the detector fire.
    far_idx = np.flatnonzero((g_range >= p.far_range[0]) & (g_range < p.far_range[1]))
    f = min(int(rng.poisson(p.far_rate)), len(far_idx))
    far = _ground_boxes(ground_points[rng.choice(far_idx, f, replace=False)] if f else np.zeros((0, 3)), ground_z,
                        rng, f, rng.beta(1.5, 3.0, f), np.zeros(f))

    boxes = Boxes.concatenate([true, moved, confusion, ghost, far])
    kind = np.array(["true"] * len(true) + ["misplaced"] * len(moved) + ["confusion"] * k + ["ghost"] * m
                    + ["far"] * f, dtype=object)
    source = np.r_[np.full(len(true) + len(moved), "-", dtype=object), names[fire],
                   np.full(m + f, "-", dtype=object)]
    order = np.argsort(-boxes.score, kind="stable")
    return boxes[order], kind[order], source[order]
