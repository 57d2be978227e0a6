"""Rotations: the package's one quaternion convention and the helpers every module uses.

**Component order is ROS's: ``(x, y, z, w)``** — ``geometry_msgs/Quaternion``, tf2 and
scipy's ``Rotation.from_quat`` all use it. Arrays are ``(..., 4)`` in that order. A source
that stores ``(w, x, y, z)`` (nuScenes, pyquaternion) converts once at its edge with
:func:`xyzw_from_wxyz` and then speaks this convention.

Yaw is the angle about +z, counter-clockwise seen from above, measured from +x (the REP 103
convention of every box in the package); :func:`yaw_from_quaternion` and
:func:`quaternion_from_yaw` are inverse for upright rotations.
"""

from __future__ import annotations

import numpy as np

from pcc_ros.errors import DataError


def xyzw_from_wxyz(q: np.ndarray) -> np.ndarray:
    """``(..., 4)`` quaternions stored ``(w, x, y, z)`` reordered to the package's ``(x, y, z, w)``."""
    q = np.asarray(q, dtype=np.float64)
    return q[..., [1, 2, 3, 0]]


def quaternion_to_matrix(q: np.ndarray) -> np.ndarray:
    """``(..., 4)`` quaternions ``(x, y, z, w)``, normalised here, -> ``(..., 3, 3)`` rotations.

    Vectorised and unchecked: a zero or non-finite quaternion gives NaN rows (callers that
    read untrusted input validate first, or use :func:`quaternion_matrix`).
    """
    q = np.asarray(q, dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def quaternion_matrix(x: float, y: float, z: float, w: float) -> np.ndarray:
    """3x3 rotation of one quaternion given as x, y, z, w (ROS order), normalised here.

    Raises :class:`DataError` for a zero-length or non-finite quaternion (tf2 would too).
    """
    q = np.array([x, y, z, w], dtype=np.float64)
    norm = np.linalg.norm(q)
    if not np.isfinite(norm) or norm < 1e-12:
        raise DataError(f"invalid quaternion {q.tolist()}")
    return quaternion_to_matrix(q)


def quaternion_product(a, b) -> tuple[float, float, float, float]:
    """Hamilton product ``a * b`` of two ``(x, y, z, w)`` quaternions (rotate by ``b``, then ``a``)."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return (
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    )


def quaternion_slerp(a, b, fraction: float) -> tuple[float, float, float, float]:
    """Spherical linear interpolation from unit quaternion ``a`` (``fraction`` 0) to ``b`` (1),
    along the shorter arc (as tf2 interpolates rotations between two stamps)."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    dot = float(a @ b)
    if dot < 0.0:  # q and -q are one rotation: take the short way
        b, dot = -b, -dot
    if dot > 1.0 - 1e-9:  # (nearly) the same rotation: a straight line is exact enough
        out = a + fraction * (b - a)
    else:
        theta = np.arccos(dot)
        out = (np.sin((1.0 - fraction) * theta) * a + np.sin(fraction * theta) * b) / np.sin(theta)
    out = out / np.linalg.norm(out)
    return tuple(float(v) for v in out)


def yaw_from_quaternion(q: np.ndarray) -> np.ndarray:
    """Yaw of ``(N, 4)`` unit quaternions ``(x, y, z, w)``: heading of the rotated x axis."""
    x, y, z, w = np.asarray(q, dtype=np.float64).T
    return np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def quaternion_from_yaw(yaw: np.ndarray | float) -> np.ndarray:
    """``(..., 4)`` quaternions ``(x, y, z, w)`` of rotations by ``yaw`` about +z."""
    half = np.asarray(yaw, dtype=np.float64) / 2.0
    zero = np.zeros_like(half)
    return np.stack([zero, zero, np.sin(half), np.cos(half)], axis=-1)


def tilt_from_quaternion(q: np.ndarray) -> np.ndarray:
    """Angle between the rotated z axis of ``(N, 4)`` unit quaternions ``(x, y, z, w)`` and vertical, radians."""
    q = np.asarray(q, dtype=np.float64)
    x, y = q[:, 0], q[:, 1]
    return np.arccos(np.clip(1.0 - 2.0 * (x * x + y * y), -1.0, 1.0))


def rotation_z(yaw: np.ndarray | float) -> np.ndarray:
    """``(..., 3, 3)`` rotations by ``yaw`` about +z (a scalar yaw gives one 3x3 matrix)."""
    c, s = np.cos(yaw), np.sin(yaw)
    z, o = np.zeros_like(c), np.ones_like(c)
    return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2)
