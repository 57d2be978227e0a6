"""TraPCC's shape-mismatch filter (TraPCC paper §4.5 and §5.2).

Each detection is completed; if the detector boxed something that is not a vehicle (a
bush, a pole, a wall, empty space), the completion network — which only knows cars —
produces a car that does not explain the raw points. The mismatch between the raw crop
and its completion is measured by

* MCD (TraPCC Eq. 2): the mean squared distance from each raw point to its nearest
  completed point (canonical units, i.e. fractions of the box length), and
* 2D contour differences in the side (x-z), front (y-z) and top (x-y) views: the
  fraction of the raw crop's occupied silhouette cells that the completion's (slightly
  dilated) silhouette does not cover, averaged over the three views,

folded into one score in [0, 1): ``1 - exp(-(mcd / mcd_scale + contour / contour_scale))``.
A detection is rejected when its mismatch score is above ``match_threshold`` AND its
(mapped) detection score is below ``detection_threshold`` — confident detections are
never removed by shape alone (0.3 / 0.5 on KITTI in the paper).

Detector scores are not always probabilities (PointRCNN gives logits): ``score_mapping``
makes the conversion explicit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pcc_ros.errors import ConfigError
from pcc_ros.metrics.chamfer import nearest_distances_batch

SCORE_MAPPINGS = ("identity", "sigmoid")
_VIEWS = ((0, 2), (1, 2), (0, 1))  # side (x-z), front (y-z), top (x-y)


@dataclass(frozen=True)
class FilterConfig:
    match_threshold: float = 0.3
    detection_threshold: float = 0.5
    score_mapping: str = "identity"
    mcd_scale: float = 0.0025  # canonical units squared: (5 % of the car length)^2
    contour_scale: float = 0.5
    grid_cells: int = 24
    grid_extent: float = 0.75  # canonical half-extent of the silhouette grid

    def __post_init__(self) -> None:
        if self.score_mapping not in SCORE_MAPPINGS:
            raise ConfigError(f"score_mapping must be one of {SCORE_MAPPINGS}, got {self.score_mapping!r}")
        if not (self.mcd_scale > 0 and self.contour_scale > 0 and self.grid_cells > 1):
            raise ConfigError("mcd_scale, contour_scale must be > 0 and grid_cells > 1")


def map_scores(scores: np.ndarray, mapping: str) -> np.ndarray:
    """Detector scores -> probabilities in [0, 1] (``identity`` or ``sigmoid`` of logits)."""
    scores = np.asarray(scores, dtype=np.float64)
    if mapping == "identity":
        return scores
    if mapping == "sigmoid":
        return 1.0 / (1.0 + np.exp(-scores))
    raise ConfigError(f"unknown score_mapping {mapping!r}")


def _stack(clouds: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """All clouds in one array, with the instance index of each point."""
    sizes = np.array([len(c) for c in clouds], dtype=np.int64)
    points = np.concatenate(clouds).astype(np.float64) if sizes.sum() else np.zeros((0, 3))
    return points, np.repeat(np.arange(len(clouds)), sizes)


def _silhouettes(points: np.ndarray, owner: np.ndarray, n: int, view: tuple[int, int], config: FilterConfig):
    """``(n, cells, cells)`` occupancy of every instance's cloud in one 2D view."""
    cells, extent = config.grid_cells, config.grid_extent
    ij = np.clip(np.floor((points[:, list(view)] + extent) / (2 * extent) * cells).astype(np.int64), 0, cells - 1)
    flat = (owner * cells + ij[:, 0]) * cells + ij[:, 1]
    grid = np.zeros(n * cells * cells, dtype=bool)
    grid[flat] = True
    return grid.reshape(n, cells, cells)


def _dilate(grid: np.ndarray) -> np.ndarray:
    """3x3 dilation of a batch of ``(n, cells, cells)`` occupancy grids."""
    cells = grid.shape[1]
    padded = np.pad(grid, ((0, 0), (1, 1), (1, 1)))
    out = np.zeros_like(grid)
    for di in range(3):
        for dj in range(3):
            out |= padded[:, di : di + cells, dj : dj + cells]
    return out


def contour_differences(partials: list[np.ndarray], completions: list[np.ndarray], config: FilterConfig) -> np.ndarray:
    """Per instance, the mean over the side / front / top views of the share of the crop's
    occupied silhouette cells that the (dilated) completion silhouette misses. One pass for all."""
    n = len(partials)
    p_points, p_owner = _stack(partials)
    c_points, c_owner = _stack(completions)
    misses = np.zeros(n)
    for view in _VIEWS:
        theirs = _silhouettes(c_points, c_owner, n, view, config)
        covered = _dilate(theirs).reshape(-1)
        mine = _silhouettes(p_points, p_owner, n, view, config)
        occupied = np.flatnonzero(mine.reshape(-1))  # each occupied cell once
        owner = occupied // (config.grid_cells**2)
        missed = np.bincount(owner, weights=~covered[occupied], minlength=n)
        total = np.bincount(owner, minlength=n)
        misses += np.divide(missed, total, out=np.zeros(n), where=total > 0)
    return misses / len(_VIEWS)


def mcd(partials: list[np.ndarray], completions: list[np.ndarray]) -> np.ndarray:
    """TraPCC's MCD (Eq. 2) per instance: the mean *squared* distance from each crop point to
    its nearest completed point, canonical units. Pairs with an empty side get ``inf``."""
    out = np.full(len(partials), np.inf)
    ok = [k for k, (p, c) in enumerate(zip(partials, completions)) if len(p) and len(c)]
    if ok:
        distances = nearest_distances_batch([partials[k] for k in ok], [completions[k] for k in ok])
        out[ok] = [float(np.mean(d**2)) for d in distances]
    return out


def mismatch_terms(partial: np.ndarray, completion: np.ndarray, config: FilterConfig) -> tuple[float, float]:
    """(MCD, contour difference) of one canonical crop and its canonical completion (diagnostics)."""
    return float(mcd([partial], [completion])[0]), float(contour_differences([partial], [completion], config)[0])


def mismatch_scores(
    partials: list[np.ndarray], completions: list[np.ndarray], config: FilterConfig
) -> np.ndarray:
    """Mismatch score in [0, 1] for each (crop, completion) pair, both canonical (batched)."""
    if not partials:
        return np.zeros(0)
    terms = mcd(partials, completions) / config.mcd_scale  # inf where a side is empty: score 1
    terms += contour_differences(partials, completions, config) / config.contour_scale
    return 1.0 - np.exp(-terms)


def reject_mask(mismatch: np.ndarray, detection_scores: np.ndarray, config: FilterConfig) -> np.ndarray:
    """True where a detection is rejected: shape mismatch high AND detection score low.

    A detection with no mismatch score (NaN: too few points to judge) is kept — absence
    of evidence is not a reason to drop a detection.
    """
    probability = map_scores(detection_scores, config.score_mapping)
    mismatch = np.asarray(mismatch, dtype=np.float64)
    judged = np.isfinite(mismatch)
    return judged & (np.where(judged, mismatch, 0.0) > config.match_threshold) & (
        probability < config.detection_threshold
    )
