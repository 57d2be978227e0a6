"""Rigid transforms of boxes between frames (e.g. detections stamped in ``base_link``
while the scan is in the LiDAR frame, resolved through tf2 by the nodes)."""

from __future__ import annotations

import numpy as np

from pcc_ros.geometry.rotations import quaternion_matrix
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
