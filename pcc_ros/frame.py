"""One LiDAR frame with its boxes: the unit every reader yields and every tool consumes.

KITTI, nuScenes and SynthCars readers, and the bag reader, all produce
:class:`Frame` objects, so conversion, instance extraction, replay and evaluation
are written once against this type.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pcc_ros.boxes import Boxes


@dataclass
class Frame:
    """A scan and its annotations, all in the sensor frame ``frame_id``.

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
