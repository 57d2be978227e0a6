"""TraPCC's completion metrics that need no complete ground truth.

* **fidelity** ("L-I", TraPCC Eq. 2, the MCD): mean *squared* distance from each *input*
  point to its nearest *completed* point. A completion that drops or moves the observed
  points scores badly; it is blind to what is added elsewhere, which is why it is paired
  with a reference-based metric. Unit: length squared.
* **side-view Chamfer** ("L-S"): the TraPCC Eq. 1 Chamfer (mean squared distances, summed
  over both directions) between the 2D side-view projections of the completion and of a
  reference cloud: the canonical x-z plane (drop y), so the silhouette seen from the car's
  side is compared, which a sparse reference (e.g. several frames of one track aggregated,
  the PointPnCNet KITTI protocol) constrains much better than in 3D. Unit: length squared.

Both are computed in the canonical frame by the evaluation and scaled by the box length
squared to square metres.
"""

from __future__ import annotations

import numpy as np

from pcc_ros.metrics.chamfer import nearest_distances

#: Canonical axes kept by the side view: x (along the car) and z (up).
SIDE_VIEW_AXES = (0, 2)


def fidelity(partial: np.ndarray, completion: np.ndarray) -> float:
    """TraPCC L-I / MCD: mean squared NN distance input -> completion."""
    return float(np.square(nearest_distances(partial, completion)).mean())


def side_view_cd(completion: np.ndarray, reference: np.ndarray, axes: tuple[int, int] = SIDE_VIEW_AXES) -> float:
    """TraPCC L-S: squared-distance Chamfer (summed both ways) of the 2D side projections."""
    a = np.asarray(completion, dtype=np.float64)[:, list(axes)]
    b = np.asarray(reference, dtype=np.float64)[:, list(axes)]
    return float(np.square(nearest_distances(a, b)).mean() + np.square(nearest_distances(b, a)).mean())
