"""The canonical car frame and its exact inverse.

Canonical frame (see DESIGN.md): origin at the box centre, x toward the car's front,
y left, z up, scaled isotropically by ``1 / box length`` so the car spans about
[-0.5, 0.5] in x. Every completion backend consumes and produces canonical clouds;
this module is the only place that converts, so the two directions cannot drift.

:func:`to_box_local` is the box-frame transform (points relative to a box centre, rotated
by minus its yaw): the canonical frame is it scaled by ``1 / length``. The scan-sized hot
loops (the exact test of ``geometry/boxes.BoxCandidates`` and the filter's measurements in
``pipeline/evidence``) write the same rotation inline into their reused work arrays instead,
to avoid its temporaries.
"""

from __future__ import annotations

import numpy as np

from pcc_ros.geometry.rotations import rotation_z


def to_box_local(x, y, z, cx, cy, cz, cos, sin) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points given as coordinate columns in the frame of a box: origin at its centre
    ``(cx, cy, cz)``, x along its heading (``cos``, ``sin`` of its yaw), z up; metres.

    Every argument is an array (one value per point: a per-pair gather of the box's values)
    or anything that broadcasts against the points. Computed in the arrays' own dtype
    (float32 columns stay float32) as ``(cos dx + sin dy, cos dy - sin dx, dz)``.
    """
    dx = x - cx
    dy = y - cy
    return cos * dx + sin * dy, cos * dy - sin * dx, z - cz


def to_canonical(points: np.ndarray, center: np.ndarray, yaw: float, length: float) -> np.ndarray:
    """Sensor-frame ``(N, 3)`` points of one box into its canonical frame."""
    p = np.asarray(points, dtype=np.float64)[:, :3]
    center = np.asarray(center, dtype=np.float64)
    local = to_box_local(p[:, 0], p[:, 1], p[:, 2], *center, np.cos(yaw), np.sin(yaw))
    return np.stack(local, axis=1) / length


def from_canonical(points: np.ndarray, center: np.ndarray, yaw: float, length: float) -> np.ndarray:
    """Exact inverse of :func:`to_canonical`."""
    c, s = np.cos(yaw), np.sin(yaw)
    p = np.asarray(points, dtype=np.float64)[:, :3] * length
    x = c * p[:, 0] - s * p[:, 1]
    y = s * p[:, 0] + c * p[:, 1]
    return np.stack([x, y, p[:, 2]], axis=1) + np.asarray(center, dtype=np.float64)


def to_canonical_batch(points: np.ndarray, center: np.ndarray, yaw: np.ndarray, length: np.ndarray) -> np.ndarray:
    """``(B, N, 3)`` sensor points, one box per batch row, into canonical frames."""
    p = np.asarray(points, dtype=np.float64)[..., :3]
    center = np.asarray(center, dtype=np.float64)[:, None, :]
    yaw = np.asarray(yaw, dtype=np.float64)[:, None]
    local = to_box_local(p[..., 0], p[..., 1], p[..., 2], *np.moveaxis(center, -1, 0), np.cos(yaw), np.sin(yaw))
    return np.stack(local, axis=-1) / np.asarray(length, dtype=np.float64)[:, None, None]


def from_canonical_batch(points: np.ndarray, center: np.ndarray, yaw: np.ndarray, length: np.ndarray) -> np.ndarray:
    """Exact inverse of :func:`to_canonical_batch`."""
    rot = rotation_z(np.asarray(yaw, dtype=np.float64))
    p = np.asarray(points, dtype=np.float64)[..., :3] * np.asarray(length, dtype=np.float64)[:, None, None]
    return np.einsum("bnk,bjk->bnj", p, rot) + np.asarray(center, dtype=np.float64)[:, None, :]


def mirror_y(points: np.ndarray) -> np.ndarray:
    """The reflection of canonical ``points`` across the box's x-z plane (``y -> -y``), the left /
    right symmetry of a car; extra columns after x, y, z (flags, intensity) are kept as they are."""
    out = np.array(points, copy=True)
    out[..., 1] = -out[..., 1]
    return out
