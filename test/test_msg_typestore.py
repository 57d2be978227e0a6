"""Type store (vision_msgs 4.x registered, RIHS01), flavour-neutral construction, stamps."""

from __future__ import annotations

import array

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from pcc_ros.errors import MessageError
from pcc_ros.msg.stamps import make_header, ns_to_stamp, stamp_to_ns
from pcc_ros.msg.typestore import (
    VISION_MSGS,
    byte_array,
    get_typestore,
    new_message,
    rosbags_classes,
    type_hash,
)


def test_store_is_cached_and_has_vision_and_jazzy_types():
    store = get_typestore()
    assert store is get_typestore()
    for name in [*VISION_MSGS, "sensor_msgs/msg/PointCloud2", "visualization_msgs/msg/MarkerArray"]:
        assert name in store.types
    fields = [name for name, _ in store.fielddefs["vision_msgs/msg/Detection3D"][1]]
    assert fields == ["header", "results", "bbox", "id"]
    fields = [name for name, _ in store.fielddefs["vision_msgs/msg/ObjectHypothesisWithPose"][1]]
    assert fields == ["hypothesis", "pose"]
    assert [n for n, _ in store.fielddefs["vision_msgs/msg/ObjectHypothesis"][1]] == ["class_id", "score"]
    assert [n for n, _ in store.fielddefs["vision_msgs/msg/BoundingBox3D"][1]] == ["center", "size"]


def test_rihs01_hashes():
    # Values published for vision_msgs 4.x on Jazzy (cross-checked against an independent
    # ROS 2 client implementation); PointCloud2's is rosbags' own Jazzy value.
    assert type_hash("vision_msgs/msg/Detection3DArray") == (
        "RIHS01_793f5eab9595ac1c0da07873cc859db42eae51f0ee76056db8562515d830e018"
    )
    assert type_hash("vision_msgs/msg/Detection3D") == (
        "RIHS01_ddd703be132ab0b69d33121f1bb034132bfbb3b0ac5f9fb1516005ba1c8a265b"
    )
    assert type_hash("sensor_msgs/msg/PointCloud2").startswith("RIHS01_")
    with pytest.raises(MessageError, match="unknown message type"):
        type_hash("vision_msgs/msg/Nope")


def test_rosbags_classes_and_defaults_serialise():
    store = get_typestore()
    with pytest.raises(MessageError, match="unknown message type 'foo/msg/Bar'"):
        rosbags_classes("foo/msg/Bar")
    for name in [*VISION_MSGS, "visualization_msgs/msg/Marker"]:
        msg = new_message(name)  # every required rosbags field filled with zero values
        assert isinstance(msg, rosbags_classes(name))
        back = store.deserialize_cdr(store.serialize_cdr(msg, name), name)
        assert type(back) is type(msg)
    cov = new_message("geometry_msgs/msg/PoseWithCovariance").covariance
    assert isinstance(cov, np.ndarray) and cov.shape == (36,) and cov.dtype == np.float64


def test_byte_array_per_flavour():
    data = np.arange(5, dtype=np.uint8)
    assert byte_array(rosbags_classes("sensor_msgs/msg/PointCloud2"), data) is data

    class Other:  # any non-rosbags class (rclpy's, in production) gets array.array('B')
        pass

    out = byte_array(Other, data)
    assert isinstance(out, array.array) and out.typecode == "B" and list(out) == [0, 1, 2, 3, 4]


@given(st.integers(-(2**31) * 10**9, (2**31 - 1) * 10**9 + 999_999_999))
def test_stamp_round_trip(ns):
    stamp = ns_to_stamp(ns)
    assert 0 <= stamp.nanosec < 10**9
    assert stamp_to_ns(stamp) == ns


def test_stamp_examples_and_errors():
    assert (ns_to_stamp(-1).sec, ns_to_stamp(-1).nanosec) == (-1, 999_999_999)
    header = make_header("base_link", 1_500_000_000_000_000_001)
    assert header.frame_id == "base_link" and (header.stamp.sec, header.stamp.nanosec) == (1_500_000_000, 1)
    with pytest.raises(MessageError, match="does not fit"):
        ns_to_stamp(2**31 * 10**9)
    with pytest.raises(MessageError, match=r"nanosec 1000000000 is outside \[0, 1e9\)"):
        stamp_to_ns(new_message("builtin_interfaces/msg/Time", sec=0, nanosec=10**9))
    with pytest.raises(MessageError, match="not a builtin_interfaces/Time"):
        stamp_to_ns(object())
