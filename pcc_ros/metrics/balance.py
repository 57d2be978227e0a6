"""Far-side and over-time figures of a completion: lateral balance, the unseen half's
completeness, and temporal consistency along a track.

A LiDAR sees one side of a car; a completion is worth most where the sensor did not look.
These figures say whether the far side is filled and whether a car's completion holds
still from one frame to the next (so a backend cannot buy completeness with flicker):

* ``lateral_offset``: ``|mean y|`` of a cloud in the box frame. A car is left / right
  symmetric, so a completion whose points crowd the seen flank has a large offset
  (the front view's balance).
* ``far_completeness``: mean distance from each *reference* point in the box half away
  from the sensor to the nearest completion point. The half is split by the vertical plane
  through the box centre perpendicular to the horizontal direction to the sensor, so a car
  seen from its flank has its other flank as the unseen half, one seen from behind its front.
* ``consistency``: symmetric Chamfer-L1 (``(mean d(a, B) + mean d(b, A)) / 2``) between
  the completions of one track in consecutive frames, in the box frame (PoinTr's KITTI
  Consistency, with the non-squared Chamfer the other tables use). Each pair is credited to
  the later frame; a track's first frame (or one after a gap) has none (NaN).

Everything here works on canonical clouds (box centre, x forward, y left, z up, divided by
the box length); multiply by the box length for metres.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from pcc_ros.metrics.chamfer import PairDistances, chamfer_from_distances, nearest_distances


def lateral_offset(cloud: np.ndarray) -> float:
    """``|mean y|`` of a canonical cloud (NaN when empty)."""
    pts = np.asarray(cloud, dtype=np.float64).reshape(-1, 3)
    return abs(float(pts[:, 1].mean())) if len(pts) else float("nan")


def far_half_mask(points: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """Which canonical ``points`` lie in the box half away from the sensor at canonical ``origin``.

    The split is the vertical plane through the box centre perpendicular to the horizontal
    direction to the sensor; a sensor straight above the centre (no horizontal direction)
    leaves no far half (all ``False``)."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    direction = np.asarray(origin, dtype=np.float64)[:2]
    norm = float(np.hypot(*direction))
    if norm < 1e-9:
        return np.zeros(len(pts), dtype=bool)
    return pts[:, :2] @ (direction / norm) < 0.0


def far_completeness(reference: np.ndarray, completion: np.ndarray, origin: np.ndarray) -> float:
    """Mean distance from the reference's points in the far half to the nearest completion point
    (canonical units; NaN when the reference holds no far-half point or the completion is empty)."""
    ref = np.asarray(reference, dtype=np.float64).reshape(-1, 3)
    far = ref[far_half_mask(ref, origin)]
    comp = np.asarray(completion, dtype=np.float64).reshape(-1, 3)
    if len(far) == 0 or len(comp) == 0:
        return float("nan")
    return float(nearest_distances(far, comp).mean())


def symmetric_chamfer_l1(a: np.ndarray, b: np.ndarray) -> float:
    """``(mean d(a, B) + mean d(b, A)) / 2`` (NaN when either cloud is empty)."""
    a = np.asarray(a, dtype=np.float64).reshape(-1, 3)
    b = np.asarray(b, dtype=np.float64).reshape(-1, 3)
    if len(a) == 0 or len(b) == 0:
        return float("nan")
    return float(chamfer_from_distances(PairDistances.compute(a, b))["cd_l1"])


def previous_in_track(tracks: Sequence[str], frames: Sequence[int]) -> np.ndarray:
    """Per instance: the index of the same track's observation just before it (by frame; -1 for
    a track's first one and for instances without a track key). Parallel inputs in any order;
    one sort. What consistency compares, and what a training pair of neighbouring frames is."""
    keys = np.asarray([str(t) for t in tracks])
    frame = np.asarray(frames, dtype=np.int64)
    if len(keys) != len(frame):
        raise ValueError(f"previous_in_track: {len(keys)} tracks, {len(frame)} frames")
    order = np.lexsort((frame, keys))
    out = np.full(len(keys), -1, dtype=np.int64)
    same = (keys[order[1:]] == keys[order[:-1]]) & (keys[order[1:]] != "")
    out[order[1:][same]] = order[:-1][same]
    return out


def track_partners(sequence: np.ndarray, track: np.ndarray, frame: np.ndarray) -> np.ndarray:
    """For each observation, the index of the same track's observation in the next frame it was
    seen in (the previous one for a track's last frame); itself for a track seen once or an
    observation without a track id (``""``). Vectorised (:func:`previous_in_track`'s one sort).
    The training pairs of the recipes' consistency terms (AML's code gap, TraPCC's Chamfer
    between the two completions), so training and ``consistency`` pair the same frames."""
    track = np.asarray(track, str)
    keys = np.where(track == "", "", np.char.add(np.char.add(np.asarray(sequence, str), "/"), track))
    previous = previous_in_track(keys, frame)
    has_previous = np.flatnonzero(previous >= 0)
    following = np.full(len(keys), -1, dtype=np.int64)
    following[previous[has_previous]] = has_previous
    return np.where(following >= 0, following, np.where(previous >= 0, previous, np.arange(len(keys))))


def track_consistency(
    tracks: Sequence[str], frames: Sequence[int], clouds: Sequence[np.ndarray], max_gap: int = 1
) -> np.ndarray:
    """Per instance: the symmetric Chamfer-L1 between its cloud and the cloud of the same track's
    previous observation, when that one is at most ``max_gap`` frames earlier (NaN otherwise).

    ``tracks`` / ``frames`` / ``clouds`` are parallel (any order); canonical units. Only
    instances with a track key take part (an empty key has no history)."""
    n = len(clouds)
    if not (len(tracks) == len(frames) == n):
        raise ValueError(f"track_consistency: {len(tracks)} tracks, {len(frames)} frames, {n} clouds")
    out = np.full(n, np.nan)
    frame = np.asarray(frames, dtype=np.int64)
    previous = previous_in_track(tracks, frame)
    for cur in np.flatnonzero(previous >= 0):  # one pair per consecutive observation (tens to thousands)
        prev = previous[cur]
        if 0 < frame[cur] - frame[prev] <= max_gap:
            out[cur] = symmetric_chamfer_l1(clouds[prev], clouds[cur])
    return out
