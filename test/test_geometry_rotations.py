"""The one quaternion convention (x, y, z, w) checked against scipy's (also x, y, z, w)."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pcc_ros.errors import DataError
from pcc_ros.geometry.rotations import (
    quaternion_from_yaw,
    quaternion_matrix,
    quaternion_product,
    quaternion_to_matrix,
    rotation_z,
    tilt_from_quaternion,
    xyzw_from_wxyz,
    yaw_from_quaternion,
)


def test_matrix_matches_scipy_in_ros_order():
    q = np.random.default_rng(1).normal(size=(6, 4))
    np.testing.assert_allclose(quaternion_to_matrix(q), Rotation.from_quat(q).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(quaternion_matrix(*q[0]), Rotation.from_quat(q[0]).as_matrix(), atol=1e-12)


def test_wxyz_sources_convert_once():
    wxyz = np.array([np.cos(0.4), 0.0, 0.0, np.sin(0.4)])  # 0.8 rad about +z, stored w first
    np.testing.assert_allclose(yaw_from_quaternion(xyzw_from_wxyz(wxyz)[None]), [0.8])


def test_invalid_quaternion_is_a_data_error():
    with pytest.raises(DataError, match="invalid quaternion"):
        quaternion_matrix(0.0, 0.0, 0.0, 0.0)


def test_product_composes_like_scipy():
    rng = np.random.default_rng(2)
    a, b = (Rotation.random(random_state=int(s)) for s in rng.integers(0, 1000, 2))
    ours = np.array(quaternion_product(a.as_quat(), b.as_quat()))
    np.testing.assert_allclose(Rotation.from_quat(ours).as_matrix(), (a * b).as_matrix(), atol=1e-12)


def test_yaw_round_trip_tilt_and_rotation_z():
    yaw = np.array([-3.0, -1.2, 0.0, 0.7, 2.9])
    q = quaternion_from_yaw(yaw)
    np.testing.assert_allclose(yaw_from_quaternion(q), yaw, atol=1e-12)
    np.testing.assert_allclose(tilt_from_quaternion(q), 0.0, atol=1e-7)
    np.testing.assert_allclose(rotation_z(yaw), quaternion_to_matrix(q), atol=1e-12)
    rolled = Rotation.from_euler("xyz", [0.3, 0.0, 1.0]).as_quat()[None]
    np.testing.assert_allclose(tilt_from_quaternion(rolled), [0.3], atol=1e-12)
    np.testing.assert_allclose(yaw_from_quaternion(rolled), [1.0], atol=1e-12)
    assert rotation_z(0.5).shape == (3, 3)
