"""Rigid transforms of boxes between frames (e.g. detections stamped in ``base_link``
while the scan is in the LiDAR frame, resolved through tf2 by the nodes)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pcc_ros.geometry.rotations import quaternion_matrix, quaternion_product, quaternion_slerp
from pcc_ros.types import Boxes


def wrap_angle(angle: np.ndarray | float) -> np.ndarray:
    """Angles wrapped to (-pi, pi]."""
    return np.angle(np.exp(1j * np.asarray(angle, dtype=np.float64)))


def transform_matrix(
    translation: tuple[float, float, float], quaternion: tuple[float, float, float, float]
) -> np.ndarray:
    """4x4 homogeneous transform from a translation and an x, y, z, w quaternion."""
    out = np.eye(4)
    out[:3, :3] = quaternion_matrix(*quaternion)
    out[:3, 3] = translation
    return out


@dataclass(frozen=True)
class Transform:
    """A rigid transform (translation xyz, quaternion xyzw) as tf2 returns it: it maps points
    of the source (child) frame into the target (parent) frame."""

    translation: tuple[float, float, float]
    rotation: tuple[float, float, float, float]

    def matrix(self) -> np.ndarray:
        return transform_matrix(self.translation, self.rotation)

    def __matmul__(self, other: Transform) -> Transform:
        """``self @ other``: first ``other``, then ``self`` (``a <- b`` @ ``b <- c`` = ``a <- c``)."""
        rotated = quaternion_matrix(*self.rotation) @ np.asarray(other.translation, dtype=np.float64)
        translation = rotated + np.asarray(self.translation, dtype=np.float64)
        rotation = np.asarray(quaternion_product(self.rotation, other.rotation), dtype=np.float64)
        rotation = rotation / np.linalg.norm(rotation)
        return Transform(tuple(float(v) for v in translation), tuple(float(v) for v in rotation))

    def inverse(self) -> Transform:
        x, y, z, w = (float(v) for v in self.rotation)
        translation = -(quaternion_matrix(x, y, z, w).T @ np.asarray(self.translation, dtype=np.float64))
        return Transform(tuple(float(v) for v in translation), (-x, -y, -z, w))

    def interpolate(self, other: Transform, fraction: float) -> Transform:
        """The transform ``fraction`` of the way to ``other``: translation linear, rotation slerp (tf2's rule)."""
        a, b = np.asarray(self.translation, dtype=np.float64), np.asarray(other.translation, dtype=np.float64)
        translation = a + fraction * (b - a)
        rotation = quaternion_slerp(self.rotation, other.rotation, fraction)
        return Transform(tuple(float(v) for v in translation), rotation)


IDENTITY = Transform((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))


def transform_boxes(boxes: Boxes, matrix: np.ndarray) -> Boxes:
    """Boxes expressed in a new frame: ``matrix`` maps points of the old frame into the new.

    Centres are transformed exactly; the heading is the rotated box x axis projected on
    the new frame's x-y plane (boxes stay upright, as every LiDAR detector assumes).
    """
    matrix = np.asarray(matrix, dtype=np.float64)
    center = boxes.center @ matrix[:3, :3].T + matrix[:3, 3]
    heading = np.stack([np.cos(boxes.yaw), np.sin(boxes.yaw), np.zeros(len(boxes))], axis=1) @ matrix[:3, :3].T
    yaw = np.arctan2(heading[:, 1], heading[:, 0])
    return Boxes(center, boxes.size.copy(), yaw, boxes.label.copy(), boxes.score.copy(), boxes.track_id.copy())
