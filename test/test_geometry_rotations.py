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


def test_detections_moved_by_a_yawed_transform_turn_with_it():
    """transform_detections through a 30-degree yaw (an identity would hide a yaw bug)."""
    from pcc_ros.msg.detections import boxes_from_detection_array, detection_array_from_boxes, transform_detections
    from pcc_ros.runtime.base import Transform
    from pcc_ros.types import Boxes

    boxes = Boxes([[10.0, 2.0, -0.8], [-4.0, 7.0, -0.7]], [[4.2, 1.8, 1.5], [4.5, 1.9, 1.6]], [0.2, -2.5],
                  ["Car", "Car"], [0.9, 0.7], ["a", "b"])
    turn = np.pi / 6
    transform = Transform((1.0, -2.0, 0.5), tuple(quaternion_from_yaw(turn).tolist()))
    array = detection_array_from_boxes(boxes, "base_link", 1)
    moved = transform_detections(array.detections, transform, "velodyne")
    array.detections = moved
    out = boxes_from_detection_array(array)
    expected = boxes.center @ rotation_z(turn).T + [1.0, -2.0, 0.5]
    np.testing.assert_allclose(out.center, expected, atol=1e-9)
    np.testing.assert_allclose(np.cos(out.yaw - boxes.yaw - turn), 1.0, atol=1e-12)
    assert all(d.header.frame_id == "velodyne" for d in moved)
    hypothesis = moved[1].results[0].pose.pose
    assert (hypothesis.position.x, hypothesis.position.y) == pytest.approx(tuple(expected[1, :2]))
    assert yaw_from_quaternion(np.array([[hypothesis.orientation.x, hypothesis.orientation.y,
                                          hypothesis.orientation.z, hypothesis.orientation.w]]))[0] == pytest.approx(
        np.angle(np.exp(1j * (boxes.yaw[1] + turn))))
