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

* **L-G** (TraPCC §5.2): the Eq. 1 Chamfer (squared, summed both ways) between the
  completion and the retrieved pseudo ground truth (:mod:`pcc_ros.data.gt_pools`), averaged
  over the Whole-GT and, where the input has that half and the Partial-GT pool an entry, the
  front / back Partial-GT compared with the completion's same half.
* **meanCD**: the mean of L-G, L-I and L-S, where L-S is then the side-view Chamfer
  against the retrieved Whole-GT (:func:`gt_free_metrics`).

All are computed in the canonical frame by the evaluation and scaled by the box length
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


def chamfer_l2_pair(a: np.ndarray, b: np.ndarray) -> float:
    """TraPCC Eq. 1: mean squared NN distance a -> b plus b -> a."""
    return float(np.square(nearest_distances(a, b)).mean() + np.square(nearest_distances(b, a)).mean())


def gt_free_metrics(completion: np.ndarray, partial: np.ndarray, pseudo_gt: dict[str, np.ndarray | None]
                    ) -> dict[str, float]:
    """TraPCC's L-G, L-I, L-S and meanCD of one completion against its retrieved pseudo GT.

    ``pseudo_gt``: ``whole`` (required), ``front`` / ``back`` (``None`` when not retrieved).
    Halves of the completion are split like the input (canonical x >= 0 is the front).
    """
    pred = np.asarray(completion, dtype=np.float64)
    terms = [chamfer_l2_pair(pred, pseudo_gt["whole"])]
    for name, mask in (("front", pred[:, 0] >= 0), ("back", pred[:, 0] < 0)):
        ref = pseudo_gt.get(name)
        if ref is not None and len(ref) and mask.any():
            terms.append(chamfer_l2_pair(pred[mask], ref))
    l_g = float(np.mean(terms))
    l_i = fidelity(partial, pred)
    l_s = side_view_cd(pred, pseudo_gt["whole"])
    return {"l_g": l_g, "l_i": l_i, "l_s": l_s, "mean_cd": (l_g + l_i + l_s) / 3.0}


def side_view_cd(completion: np.ndarray, reference: np.ndarray, axes: tuple[int, int] = SIDE_VIEW_AXES) -> float:
    """TraPCC L-S: squared-distance Chamfer (summed both ways) of the 2D side projections."""
    a = np.asarray(completion, dtype=np.float64)[:, list(axes)]
    b = np.asarray(reference, dtype=np.float64)[:, list(axes)]
    return float(np.square(nearest_distances(a, b)).mean() + np.square(nearest_distances(b, a)).mean())
