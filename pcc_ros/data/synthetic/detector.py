"""A simulated 3D car detector: ground truth made imperfect the way real detectors are.

True detections come from the labelled vehicles, missed more often the fewer LiDAR
points a car has (heavily occluded or far cars), with noise on centre, size and yaw
that grows with distance and sparsity, and an occasional heading flip. False
positives fire on clutter (each clutter object has a fixed ``confusion`` probability,
so a bush that looks like a car keeps fooling the detector frame after frame, as real
ones do) and on empty space (a random visible ground point). Scores: true detections
mostly high, false ones mostly lower, with overlap, so no score threshold separates
them and a shape-based filter has real work to do.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from pcc_ros.geometry.transforms import wrap_angle
from pcc_ros.types import Boxes


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
    empty_space_rate: float = 0.6  # Poisson mean of empty-space false positives per frame

    def to_dict(self) -> dict:
        return asdict(self)


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
) -> tuple[Boxes, np.ndarray]:
    """Detections (sensor frame) and a ``(D,)`` bool array marking the true ones.

    Args:
        gt: labelled vehicles in the sensor frame (label Car/Van).
        gt_points: ``(N,)`` visible LiDAR returns of each vehicle.
        clutter: boxes of clutter objects (bushes, walls, bins, pedestrians ...).
        clutter_points: visible returns of each clutter object.
        clutter_confusion: per-frame probability that the detector fires on each clutter object.
        ground_points: ``(G, 3)`` visible ground returns (candidate empty-space false positives).
        ground_z: ground height in the sensor frame (for box placement).
    """
    p = params or DetectorParams()
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
    true = Boxes(center, size, yaw, gt.label[hit], score)

    # False positives on clutter: a car-sized box on the object's footprint.
    cd = np.linalg.norm(clutter.center[:, :2], axis=1)
    eligible = (cd < p.clutter_range) & (clutter_points >= p.clutter_min_points)
    fire = eligible & (rng.random(len(clutter)) < clutter_confusion)
    k = int(fire.sum())
    car = np.c_[rng.normal(4.0, 0.3, k), rng.normal(1.65, 0.08, k), rng.normal(1.5, 0.08, k)]
    c = clutter.center[fire].copy()
    c[:, :2] += rng.normal(0, 0.3, (k, 2))
    c[:, 2] = ground_z + car[:, 2] / 2 + rng.normal(0, 0.05, k)
    fp_clutter = Boxes(c, car, wrap_angle(clutter.yaw[fire] + rng.normal(0, 0.3, k)), ["Car"] * k, rng.beta(2, 3.5, k))

    # False positives in empty space: a visible ground point.
    m = min(int(rng.poisson(p.empty_space_rate)), len(ground_points))
    gp = ground_points[rng.choice(len(ground_points), m, replace=False)] if m else np.zeros((0, 3))
    car = np.c_[rng.normal(3.9, 0.3, m), rng.normal(1.6, 0.08, m), rng.normal(1.5, 0.08, m)]
    c = np.c_[gp[:, :2], ground_z + car[:, 2] / 2]
    fp_empty = Boxes(c, car, rng.uniform(-np.pi, np.pi, m), ["Car"] * m, rng.beta(1.6, 4.0, m))

    boxes = Boxes.concatenate([true, fp_clutter, fp_empty])
    is_true = np.r_[np.ones(n, bool), np.zeros(k + m, bool)]
    order = np.argsort(-boxes.score, kind="stable")
    return boxes[order], is_true[order]
