"""The shared nouns: oriented 3D boxes (:class:`Boxes`), one dataset sample (:class:`Sample`)
and the class-name rule (:func:`class_mask`).

:class:`Boxes` -- oriented 3D boxes as a struct of arrays.

A box is its geometric centre (x, y, z), its size (length along the heading, width,
height) and its yaw about +z, in metres and radians in a REP 103 frame (x forward,
y left, z up). Dataset readers convert their own conventions into this once, at the
reader, so every other module sees one convention.

Struct-of-arrays (rather than a list of box objects) keeps every geometric operation
vectorised over all boxes of a frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from pcc_ros.errors import DataError


def _as_object_array(values, n: int, default: str) -> np.ndarray:
    if values is None:
        return np.full(n, default, dtype=object)
    array = np.empty(n, dtype=object)
    array[:] = list(values)
    return array


def class_mask(labels: np.ndarray, classes: tuple[str, ...] | list[str]) -> np.ndarray:
    """Labels matching ``classes`` case-insensitively, by full name or last dotted part.

    One rule for every consumer (nodes, extraction, evaluation), so ``car`` matches KITTI's
    ``Car`` and nuScenes' ``vehicle.car`` everywhere alike.
    """
    wanted = {str(c).lower() for c in classes}
    lowered = [str(v).lower() for v in labels]
    return np.array([v in wanted or v.rsplit(".", 1)[-1] in wanted for v in lowered], dtype=bool)


@dataclass
class Boxes:
    """``N`` oriented boxes. All arrays have ``N`` rows.

    Attributes:
        center: ``(N, 3)`` float64 geometric centres.
        size: ``(N, 3)`` float64 (length, width, height), length along the heading.
        yaw: ``(N,)`` float64 heading about +z, radians.
        label: ``(N,)`` object array of class names (``"Car"``, ``"Van"``, ...).
        score: ``(N,)`` float64 detector score (1.0 for ground truth); the raw value
            the detector gave, which is not always a probability.
        track_id: ``(N,)`` object array of track / instance ids as strings ("" if none).
    """

    center: np.ndarray
    size: np.ndarray
    yaw: np.ndarray
    label: np.ndarray = field(default=None)  # type: ignore[assignment]
    score: np.ndarray = field(default=None)  # type: ignore[assignment]
    track_id: np.ndarray = field(default=None)  # type: ignore[assignment]

    def __post_init__(self) -> None:
        self.center = np.asarray(self.center, dtype=np.float64).reshape(-1, 3)
        n = len(self.center)
        self.size = np.asarray(self.size, dtype=np.float64).reshape(n, 3)
        self.yaw = np.asarray(self.yaw, dtype=np.float64).reshape(n)
        self.label = _as_object_array(self.label, n, "Car")
        self.score = (
            np.ones(n, dtype=np.float64)
            if self.score is None
            else np.asarray(self.score, dtype=np.float64).reshape(n)
        )
        self.track_id = _as_object_array(self.track_id, n, "")
        if not (len(self.label) == len(self.score) == len(self.track_id) == n):
            raise DataError(f"Boxes arrays disagree in length (N={n})")

    @classmethod
    def empty(cls) -> Boxes:
        return cls(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0))

    @classmethod
    def concatenate(cls, parts: list[Boxes]) -> Boxes:
        if not parts:
            return cls.empty()
        return cls(
            np.concatenate([p.center for p in parts]),
            np.concatenate([p.size for p in parts]),
            np.concatenate([p.yaw for p in parts]),
            np.concatenate([p.label for p in parts]),
            np.concatenate([p.score for p in parts]),
            np.concatenate([p.track_id for p in parts]),
        )

    def __len__(self) -> int:
        return len(self.center)

    def __getitem__(self, index) -> Boxes:
        """Select boxes by boolean mask, integer array or slice (always returns Boxes)."""
        if isinstance(index, (int, np.integer)):
            index = [int(index)]
        return Boxes(
            self.center[index],
            self.size[index],
            self.yaw[index],
            self.label[index],
            self.score[index],
            self.track_id[index],
        )

    def mirrored(self) -> Boxes:
        """The boxes reflected across the sensor frame's x-z plane (``y -> -y``, ``yaw -> -yaw``)."""
        return Boxes(self.center * [1.0, -1.0, 1.0], self.size.copy(), -self.yaw, self.label, self.score,
                     self.track_id)

    def valid_mask(self) -> np.ndarray:
        """Boxes with finite pose and strictly positive, finite size."""
        finite = (
            np.isfinite(self.center).all(axis=1)
            & np.isfinite(self.size).all(axis=1)
            & np.isfinite(self.yaw)
        )
        return finite & (self.size > 0).all(axis=1)

    def validate(self) -> None:
        """Raise :class:`DataError` naming the first invalid box."""
        bad = np.flatnonzero(~self.valid_mask())
        if len(bad):
            i = int(bad[0])
            raise DataError(
                f"box {i} is invalid: center={self.center[i].tolist()} "
                f"size={self.size[i].tolist()} yaw={self.yaw[i]}"
            )

    def equals(self, other: Boxes, atol: float = 1e-6) -> bool:
        """Numerical equality (yaw compared modulo 2*pi), for tests and round trips."""
        if len(self) != len(other):
            return False
        dyaw = np.angle(np.exp(1j * (self.yaw - other.yaw)))
        return bool(
            np.allclose(self.center, other.center, atol=atol)
            and np.allclose(self.size, other.size, atol=atol)
            and np.all(np.abs(dyaw) <= atol)
            and np.array_equal(self.label, other.label)
            and np.allclose(self.score, other.score, atol=atol)
            and np.array_equal(self.track_id, other.track_id)
        )


@dataclass
class Sample:
    """One LiDAR scan with its boxes: the unit every reader yields and every tool consumes.

    KITTI, nuScenes and SynthCars readers, and the bag reader, all produce samples, so
    conversion, instance extraction, replay and evaluation are written once against this
    type. (Called ``Sample``, not ``Frame``: "frame" here means a coordinate frame, ``frame_id``.)

    All in the sensor frame ``frame_id``.

    Attributes:
        stamp_ns: acquisition time, integer nanoseconds.
        frame_id: the sensor frame of ``points`` and of every box.
        points: ``(N, C)`` float32; columns named by ``fields``, starting x, y, z.
        fields: column names of ``points`` (e.g. ``("x", "y", "z", "intensity")``).
        detections: detector output, or ``None`` when the source has none.
        ground_truth: annotated boxes (``track_id`` filled when tracks exist), or ``None``.
        pose: ``4x4`` float64 transform odom <- sensor frame, or ``None`` without poses.
        sequence: sequence / scene name ("0000", a nuScenes scene token, ...).
        index: frame index inside the sequence.
    """

    stamp_ns: int
    frame_id: str
    points: np.ndarray
    fields: tuple[str, ...] = ("x", "y", "z", "intensity")
    detections: Boxes | None = None
    ground_truth: Boxes | None = None
    pose: np.ndarray | None = None
    sequence: str = ""
    index: int = 0
    extras: dict = field(default_factory=dict)

    @property
    def xyz(self) -> np.ndarray:
        """``(N, 3)`` view of the coordinates."""
        return self.points[:, :3]

    def mirrored(self) -> Sample:
        """The scan of the mirror world: points, boxes and pose reflected across the sensor frame's x-z
        plane. A car seen from its left is then seen from its right, with the same returns; what
        ``pcc eval --real-mirror`` scores, so a backend that favours one flank of the box frame is
        not rewarded for the side the few real tracks happen to be seen from."""
        flip = np.diag([1.0, -1.0, 1.0, 1.0])
        points = self.points.copy()
        points[:, 1] *= -1  # what geometry.canonical.mirror_y does; types sits below geometry
        return replace(self, points=points,
                       detections=None if self.detections is None else self.detections.mirrored(),
                       ground_truth=None if self.ground_truth is None else self.ground_truth.mirrored(),
                       pose=None if self.pose is None else flip @ self.pose @ flip)
