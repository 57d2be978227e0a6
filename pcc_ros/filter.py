"""TraPCC's shape-mismatch filter (TraPCC paper §4.5 and §5.2).

Each detection is completed; if the detector boxed something that is not a vehicle (a
bush, a pole, a wall, empty space), the completion network — which only knows cars —
produces a car that does not explain the raw points. The mismatch between the raw crop
and its completion is measured by

* MCD: the mean distance from each raw point to its nearest completed point
  (canonical units, i.e. fractions of the box length), and
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
from scipy.spatial import cKDTree

from pcc_ros.errors import ConfigError

SCORE_MAPPINGS = ("identity", "sigmoid")
_VIEWS = ((0, 2), (1, 2), (0, 1))  # side (x-z), front (y-z), top (x-y)


@dataclass(frozen=True)
class FilterConfig:
    match_threshold: float = 0.3
    detection_threshold: float = 0.5
    score_mapping: str = "identity"
    mcd_scale: float = 0.05
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


def _silhouette_cells(points: np.ndarray, view: tuple[int, int], cells: int, extent: float) -> np.ndarray:
    """Flat indices of the grid cells a canonical cloud occupies in one 2D view."""
    uv = points[:, list(view)]
    ij = np.floor((uv + extent) / (2 * extent) * cells).astype(np.int64)
    ij = np.clip(ij, 0, cells - 1)
    return np.unique(ij[:, 0] * cells + ij[:, 1])


def _dilate(occupied: np.ndarray, cells: int) -> np.ndarray:
    grid = np.zeros((cells + 2, cells + 2), dtype=bool)
    grid[1:-1, 1:-1].flat[occupied] = True
    out = np.zeros((cells, cells), dtype=bool)
    for di in (0, 1, 2):
        for dj in (0, 1, 2):
            out |= grid[di : di + cells, dj : dj + cells]
    return out.ravel()


def contour_difference(partial: np.ndarray, completion: np.ndarray, config: FilterConfig) -> float:
    """Mean over the three views of the share of the crop's silhouette the completion misses."""
    misses = []
    for view in _VIEWS:
        mine = _silhouette_cells(partial, view, config.grid_cells, config.grid_extent)
        theirs = _dilate(_silhouette_cells(completion, view, config.grid_cells, config.grid_extent), config.grid_cells)
        misses.append(float(np.mean(~theirs[mine])) if len(mine) else 0.0)
    return float(np.mean(misses))


def mismatch_terms(partial: np.ndarray, completion: np.ndarray, config: FilterConfig) -> tuple[float, float]:
    """(MCD, contour difference) of one canonical crop and its canonical completion."""
    if len(partial) == 0 or len(completion) == 0:
        return float("inf"), 1.0
    distances, _ = cKDTree(completion).query(partial, k=1)
    return float(np.mean(distances)), contour_difference(partial, completion, config)


def mismatch_scores(
    partials: list[np.ndarray], completions: list[np.ndarray], config: FilterConfig
) -> np.ndarray:
    """Mismatch score in [0, 1] for each (crop, completion) pair, both canonical."""
    terms = np.array([mismatch_terms(p, c, config) for p, c in zip(partials, completions)]).reshape(-1, 2)
    return 1.0 - np.exp(-(terms[:, 0] / config.mcd_scale + terms[:, 1] / config.contour_scale))


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
