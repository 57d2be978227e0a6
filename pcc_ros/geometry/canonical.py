"""The canonical car frame and its exact inverse.

Canonical frame (see DESIGN.md): origin at the box centre, x toward the car's front,
y left, z up, scaled isotropically by ``1 / box length`` so the car spans about
[-0.5, 0.5] in x. Every completion backend consumes and produces canonical clouds;
this module is the only place that converts, so the two directions cannot drift.
"""

from __future__ import annotations

import numpy as np

from pcc_ros.geometry.rotations import rotation_z


def to_canonical(points: np.ndarray, center: np.ndarray, yaw: float, length: float) -> np.ndarray:
    """Sensor-frame ``(N, 3)`` points of one box into its canonical frame."""
    c, s = np.cos(yaw), np.sin(yaw)
    d = np.asarray(points, dtype=np.float64)[:, :3] - np.asarray(center, dtype=np.float64)
    x = (c * d[:, 0] + s * d[:, 1]) / length
    y = (-s * d[:, 0] + c * d[:, 1]) / length
    z = d[:, 2] / length
    return np.stack([x, y, z], axis=1)


def from_canonical(points: np.ndarray, center: np.ndarray, yaw: float, length: float) -> np.ndarray:
    """Exact inverse of :func:`to_canonical`."""
    c, s = np.cos(yaw), np.sin(yaw)
    p = np.asarray(points, dtype=np.float64)[:, :3] * length
    x = c * p[:, 0] - s * p[:, 1]
    y = s * p[:, 0] + c * p[:, 1]
    return np.stack([x, y, p[:, 2]], axis=1) + np.asarray(center, dtype=np.float64)


def to_canonical_batch(points: np.ndarray, center: np.ndarray, yaw: np.ndarray, length: np.ndarray) -> np.ndarray:
    """``(B, N, 3)`` sensor points, one box per batch row, into canonical frames."""
    rot = rotation_z(np.asarray(yaw, dtype=np.float64))  # (B, 3, 3) box -> sensor
    d = np.asarray(points, dtype=np.float64)[..., :3] - np.asarray(center, dtype=np.float64)[:, None, :]
    return np.einsum("bnj,bjk->bnk", d, rot) / np.asarray(length, dtype=np.float64)[:, None, None]


def from_canonical_batch(points: np.ndarray, center: np.ndarray, yaw: np.ndarray, length: np.ndarray) -> np.ndarray:
    """Exact inverse of :func:`to_canonical_batch`."""
    rot = rotation_z(np.asarray(yaw, dtype=np.float64))
    p = np.asarray(points, dtype=np.float64)[..., :3] * np.asarray(length, dtype=np.float64)[:, None, None]
    return np.einsum("bnk,bjk->bnj", p, rot) + np.asarray(center, dtype=np.float64)[:, None, :]
