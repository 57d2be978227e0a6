"""Multi-view partial ground truth of real cars: each track's crops aggregated in its canonical frame.

**Reuse this module** for anything that needs a car's observations over a sequence merged
into one cloud (the real-data evaluation ``pcc eval --real``, TraPCC's Whole-GT / Partial-GT
pools, AML's KITTI protocol)::

    from pcc_ros.data.track_aggregate import collect_tracks, aggregate_clouds, voxel_downsample

    tracks = collect_tracks(open_frames("../shared/data/kitti_tracking"), classes=("Car", "Van"))
    for key, track in tracks.items():          # "0000/3" -> Track
        gt = track.aggregate(voxel_m=0.03)     # canonical (M, 3) float32, uniform density

Motion compensation comes from the boxes: every crop is moved into its own box's canonical
car frame (``pcc_ros.geometry.canonical``: box centre, heading along +x, scaled by
``1 / length``). A rigid car occupies the same place in its own box frame at every instant,
so the crops of one track, each compensated with its own box, line up without ego poses and
whatever the car and the sensor did in between (moving cars included). The accuracy is that
of the labelled boxes (KITTI: a few centimetres, a degree or two), which is why the
aggregate is called a *partial* ground truth: it holds only what some frame saw.

``voxel_downsample`` thins the aggregate to one point per voxel, so the many near, dense
frames do not outweigh a far side seen once when a metric averages over reference points.
An instance cache stores the same canonical crops, so :func:`aggregate_instances` merges a
track's cached observations with the same :func:`aggregate_clouds`.
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pcc_ros.geometry.boxes import crop_canonical
from pcc_ros.types import Sample, class_mask

log = logging.getLogger("pcc.aggregate")


@dataclass
class Observation:
    """One crop of a tracked car: canonical points plus the box they were compensated with."""

    sequence: str
    frame: int
    track: str
    label: str
    points: np.ndarray  # (n, 3) float32, canonical frame of this frame's box
    center: np.ndarray  # (3,) box centre, sensor frame, m
    size: np.ndarray  # (3,) length, width, height, m
    yaw: float  # rad, sensor frame

    @property
    def distance(self) -> float:
        """Sensor-to-box-centre distance, metres."""
        return float(np.linalg.norm(self.center))

    @property
    def num_points(self) -> int:
        return len(self.points)

    @property
    def key(self) -> str:
        return f"{self.sequence}/{self.track}@{self.frame}"


@dataclass
class Track:
    """All observations of one car, in frame order."""

    key: str
    observations: list[Observation] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.observations)

    def aggregate(self, voxel_m: float | None = None, exclude: Iterable[int] = ()) -> np.ndarray:
        """The track's observations (minus the frame indices in ``exclude``) merged in the
        canonical frame, optionally thinned to one point per ``voxel_m`` metre voxel."""
        skip = set(int(f) for f in exclude)
        clouds = [o.points for o in self.observations if o.frame not in skip]
        length = float(np.median([o.size[0] for o in self.observations])) if self.observations else 1.0
        return aggregate_clouds(clouds, None if voxel_m is None else voxel_m / length)


def voxel_downsample(points: np.ndarray, voxel: float) -> np.ndarray:
    """One point per occupied voxel of edge ``voxel`` (the centroid of its points), vectorised."""
    pts = np.asarray(points, dtype=np.float64)[:, :3]
    if voxel <= 0 or not np.isfinite(voxel):
        raise ValueError(f"voxel size must be positive, got {voxel}")
    if len(pts) == 0:
        return np.zeros((0, 3), np.float32)
    cells = np.floor(pts / voxel).astype(np.int64)
    _, inverse, counts = np.unique(cells, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    sums = np.zeros((len(counts), 3))
    np.add.at(sums, inverse, pts)
    return (sums / counts[:, None]).astype(np.float32)


def aggregate_clouds(clouds: Iterable[np.ndarray], voxel: float | None = None) -> np.ndarray:
    """Concatenate canonical crops (already motion-compensated by their boxes), optionally
    voxel-thinned (``voxel`` in canonical units)."""
    parts = [np.asarray(c, dtype=np.float32).reshape(-1, 3) for c in clouds]
    merged = np.concatenate(parts) if parts else np.zeros((0, 3), np.float32)
    return merged if voxel is None else voxel_downsample(merged, voxel)


def aggregate_instances(cache: Any, indices: Iterable[int], voxel: float | None = None) -> np.ndarray:
    """The observations ``indices`` of an instance cache (:class:`~pcc_ros.data.instance_cache.InstanceCache`)
    merged in the canonical frame: its crops are already compensated by their boxes."""
    return aggregate_clouds((cache.points(int(i)) for i in indices), voxel)


def frame_observations(
    frame: Sample,
    classes: tuple[str, ...] = ("Car", "Van"),
    min_points: int = 1,
    margin: float = 0.0,
    ground_margin: float = 0.1,
    skipped: Counter | None = None,
) -> list[Observation]:
    """Canonical crops of the labelled, tracked boxes of one frame (the extraction's crop:
    same ``margin`` / ``ground_margin`` conventions as ``pcc extract``)."""
    skipped = Counter() if skipped is None else skipped
    boxes = frame.ground_truth
    if boxes is None or len(boxes) == 0:
        return []
    boxes = boxes[class_mask(boxes.label, classes)]
    valid = boxes.valid_mask()
    skipped["invalid_box"] += int((~valid).sum())
    boxes = boxes[valid]
    if len(boxes) == 0:
        return []
    _, crops = crop_canonical(np.asarray(frame.points), boxes, margin=margin, ground_margin=ground_margin)
    out = []
    for i, crop in enumerate(crops):  # boxes of one frame (tens); points are vectorised
        if len(crop) < max(min_points, 1):
            skipped["too_few_points"] += 1
            continue
        track = str(boxes.track_id[i])
        if not track or track == "-1":
            skipped["no_track"] += 1
            continue
        out.append(Observation(str(frame.sequence), int(frame.index), track, str(boxes.label[i]),
                               np.ascontiguousarray(crop, dtype=np.float32), boxes.center[i].copy(),
                               boxes.size[i].copy(), float(boxes.yaw[i])))
    return out


def collect_tracks(
    frames: Iterable[Sample],
    classes: tuple[str, ...] = ("Car", "Van"),
    min_points: int = 1,
    margin: float = 0.0,
    ground_margin: float = 0.1,
    frame_filter: set[int] | None = None,
    skipped: Counter | None = None,
) -> dict[str, Track]:
    """Every labelled track of ``frames`` (``sequence/track`` -> :class:`Track`, frame order).

    ``frame_filter``: only these frame indices (e.g. held-out frames). Boxes without a track
    id (single-frame datasets have none, or nuScenes instance tokens) still form tracks of
    length one; callers decide how many observations a usable track needs.
    """
    skipped = Counter() if skipped is None else skipped
    tracks: dict[str, Track] = {}
    for frame in frames:
        if frame_filter is not None and int(frame.index) not in frame_filter:
            continue
        for obs in frame_observations(frame, classes, min_points, margin, ground_margin, skipped):
            key = f"{obs.sequence}/{obs.track}"
            tracks.setdefault(key, Track(key)).observations.append(obs)
    for track in tracks.values():
        track.observations.sort(key=lambda o: o.frame)
    return tracks
