"""The DDS runtime's wire: bytes equal to rosbags' serialize_cdr, ROS 2 names, QoS, typehash, discovery config."""

from __future__ import annotations

import os
import time

import numpy as np
import pytest

pytest.importorskip("cyclonedds")

from cyclonedds.core import Policy

from pcc_ros.boxes import Boxes
from pcc_ros.errors import ConfigError, MessageError
from pcc_ros.msg.detections import detection_array_from_boxes, marker_array_from_boxes
from pcc_ros.msg.pointcloud2 import create_cloud, read_xyz
from pcc_ros.msg.stamps import make_header
from pcc_ros.msg.typestore import get_typestore, new_message, type_hash
from pcc_ros.runtime import idl
from pcc_ros.runtime.base import RELIABLE, SENSOR_DATA
from pcc_ros.runtime.discovery import Discovery
from pcc_ros.runtime.local import LocalGraph, LocalRuntime

CLOUD = "sensor_msgs/msg/PointCloud2"


def _rosbags_bytes(msg, msgtype: str) -> bytes:
    return bytes(get_typestore().serialize_cdr(msg, msgtype))


def _boxes(n: int, seed: int = 0) -> Boxes:
    rng = np.random.default_rng(seed)
    return Boxes(
        rng.normal(size=(n, 3)) * 10,
        rng.uniform(1, 5, size=(n, 3)),
        rng.uniform(-np.pi, np.pi, n),
        rng.choice(["Car", "Van", "Pedestrian"], n),
        rng.uniform(0, 1, n),
        [f"t{k}" for k in range(n)],
    )


def _clouds():
    rng = np.random.default_rng(1)
    yield "xyzi", create_cloud(rng.normal(size=(1001, 4)).astype(np.float32), ["x", "y", "z", "intensity"], "velo", 5)
    yield "empty", create_cloud(np.zeros((0, 3), np.float32), ["x", "y", "z"], "", 0)
    organized = np.zeros((4, 7), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("ring", "<u2"), ("t", "<f8")])
    organized["x"] = rng.normal(size=(4, 7))
    yield "organized-padded", create_cloud(organized, None, "lidar", -1)
    big = np.zeros(33, dtype=[("x", ">f4"), ("y", ">f4"), ("z", ">f4")])
    big["z"] = np.arange(33)
    yield "big-endian", create_cloud(big, None, "odd", 2**40)


def _diagnostics():
    status = new_message(
        "diagnostic_msgs/msg/DiagnosticStatus", level=1, name="pcc_ros: n", message="3 frames", hardware_id="pcc",
        values=[new_message("diagnostic_msgs/msg/KeyValue", key=f"k{i}", value="ü" * i) for i in range(4)],
    )
    return new_message("diagnostic_msgs/msg/DiagnosticArray", header=make_header("", 123), status=[status, status])


def _cases():
    for name, cloud in _clouds():
        yield f"cloud-{name}", CLOUD, cloud
    for n in (0, 1, 7):
        dets = detection_array_from_boxes(_boxes(n, n), "velodyne", 10**9)
        yield f"det-{n}", "vision_msgs/msg/Detection3DArray", dets
        status = np.array(["kept", "rejected", "skipped"] * 3, dtype=object)[:n]
        yield f"markers-{n}", "visualization_msgs/msg/MarkerArray", marker_array_from_boxes(
            _boxes(n, n), "velodyne", 10**9, status=status
        )
    yield "diagnostics", "diagnostic_msgs/msg/DiagnosticArray", _diagnostics()


CASES = list(_cases())


@pytest.mark.parametrize("name,msgtype,msg", CASES, ids=[c[0] for c in CASES])
def test_bytes_sent_equal_rosbags_serialize_cdr_and_decode_back(name, msgtype, msg):
    wire = idl.serialize(msgtype, msg)
    assert wire == _rosbags_bytes(msg, msgtype)
    assert wire[:4] == b"\x00\x01\x00\x00"  # CDR little endian, plain XCDR1 (no XCDR2 header)
    back = idl.deserialize(msgtype, wire)
    assert type(back) is type(msg)
    assert _rosbags_bytes(back, msgtype) == wire


def test_every_spoken_type_and_tf_is_covered_by_the_equality_cases():
    assert set(idl.SPOKEN_TYPES) <= {c[1] for c in CASES}
    # play also speaks any type of the store, e.g. /tf from converted bags.
    tf = new_message(
        "tf2_msgs/msg/TFMessage",
        transforms=[
            new_message("geometry_msgs/msg/TransformStamped", header=make_header("odom", 7), child_frame_id="b")
        ],
    )
    assert idl.serialize("tf2_msgs/msg/TFMessage", tf) == _rosbags_bytes(tf, "tf2_msgs/msg/TFMessage")


def test_point_data_travels_as_one_buffer_with_the_same_bytes_as_element_by_element():
    cloud = dict(_clouds())["xyzi"]
    fast = idl.to_idl(CLOUD, cloud)
    slow_cls = idl.idl_class(CLOUD, octets_as_buffer=False)
    slow = slow_cls(**{k: getattr(fast, k) for k in fast.__dataclass_fields__})
    slow.data = list(np.asarray(fast.data).tobytes())
    assert isinstance(idl.idl_class(CLOUD).__idl__.v1_machine.members_machines["data"], idl.OctetSequenceMachine)
    assert slow.serialize() == fast.serialize()
    # received data is a numpy view over the sample, not a list of ints
    back = idl.deserialize(CLOUD, fast.serialize())
    assert isinstance(back.data, np.ndarray) and back.data.dtype == np.uint8


def test_ros2_type_and_topic_names_final_extensibility():
    from pcc_ros.runtime.dds import dds_topic_name

    assert idl.dds_type_name(CLOUD) == "sensor_msgs::msg::dds_::PointCloud2_"
    cls = idl.idl_class(CLOUD)
    assert cls.__idl__.idl_transformed_typename == "sensor_msgs::msg::dds_::PointCloud2_"
    header_cls = cls.__annotations__["header"]
    assert header_cls.__idl_typename__ == "std_msgs::msg::dds_::Header_"
    assert header_cls.__annotations__["stamp"].__idl_typename__ == "builtin_interfaces::msg::dds_::Time_"
    assert list(cls.__annotations__) == [
        "header", "height", "width", "fields", "is_bigendian", "point_step", "row_step", "data", "is_dense",
    ]
    for msgtype in idl.SPOKEN_TYPES:
        assert idl.idl_class(msgtype).__idl__.xcdrv1_head == 0  # final: plain CDR, no DHEADER / EMHEADER
    assert dds_topic_name("/points") == "rt/points"
    assert dds_topic_name("completed", "/car") == "rt/car/completed"


def test_endpoint_qos_is_explicit_with_typehash_user_data():
    from pcc_ros.runtime.dds import endpoint_qos

    qos = endpoint_qos(SENSOR_DATA, CLOUD)
    user = next(p for p in qos if isinstance(p, Policy.Userdata))
    assert user.data == f"typehash={type_hash(CLOUD)};".encode()
    assert user.data.startswith(b"typehash=RIHS01_") and len(user.data) == len("typehash=RIHS01_;") + 64
    assert Policy.Reliability.BestEffort in qos and Policy.History.KeepLast(5) in qos
    assert Policy.Durability.Volatile in qos
    assert Policy.DataRepresentation(use_cdrv0_representation=True, use_xcdrv2_representation=False) in qos
    reliable = endpoint_qos(RELIABLE, "vision_msgs/msg/Detection3DArray")
    assert Policy.History.KeepLast(10) in reliable and Policy.Reliability.BestEffort not in reliable


def test_truncated_and_corrupt_samples_raise_message_error():
    wire = idl.serialize(CLOUD, dict(_clouds())["xyzi"])
    with pytest.raises(MessageError, match="undecodable"):
        idl.deserialize(CLOUD, wire[: len(wire) // 2])
    with pytest.raises(MessageError):
        idl.to_idl(CLOUD, object())


def test_discovery_from_environment():
    local = Discovery.from_env({"ROS_DOMAIN_ID": "42", "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"})
    assert local.domain_id == 42 and local.range == "LOCALHOST"
    xml = local.cyclone_xml()
    for part in ('<NetworkInterface address="127.0.0.1"/>', "<AllowMulticast>false</AllowMulticast>",
                 "<ParticipantIndex>auto</ParticipantIndex>", '<Peer address="127.0.0.1"/>', "SocketReceiveBufferSize"):
        assert part in xml
    subnet = Discovery.from_env({"ROS_STATIC_PEERS": "10.0.0.2; robot.local"})
    assert subnet.domain_id == 0 and subnet.range == "SUBNET"
    assert "AllowMulticast" not in subnet.cyclone_xml() and '<Peer address="robot.local"/>' in subnet.cyclone_xml()
    assert Discovery.from_env({"ROS_LOCALHOST_ONLY": "1"}).range == "LOCALHOST"
    assert Discovery.from_env({"CYCLONEDDS_URI": "file:///x.xml"}).cyclone_xml() is None
    with pytest.raises(ConfigError):
        Discovery.from_env({"ROS_DOMAIN_ID": "x"})
    with pytest.raises(ConfigError):
        Discovery.from_env({"ROS_AUTOMATIC_DISCOVERY_RANGE": "GALAXY"})


def _domain_id() -> int:
    return 100 + os.getpid() % 120


def test_in_process_dds_round_trip_and_qos_matching():
    """Two participants over loopback in one process: best-effort cloud arrives intact; RxO QoS is enforced."""
    from pcc_ros.runtime.dds import DdsRuntime, wait_for

    disc = Discovery.from_env({"ROS_DOMAIN_ID": str(_domain_id()), "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"})
    a, b = DdsRuntime("writer_side", discovery=disc), DdsRuntime("reader_side", discovery=disc)
    try:
        got, strict = [], []
        b.create_subscription("/points", CLOUD, got.append, SENSOR_DATA)
        b.create_subscription("/points_strict", CLOUD, strict.append, RELIABLE)
        b.start()
        pub = a.create_publisher("/points", CLOUD, SENSOR_DATA)
        weak = a.create_publisher("/points_strict", CLOUD, SENSOR_DATA)
        assert wait_for(lambda: pub.matched() == 1, 10)
        cloud = create_cloud(
            np.random.default_rng(3).normal(size=(120_000, 4)).astype(np.float32), ["x", "y", "z", "i"], "velo", 9
        )
        pub.publish(cloud)
        weak.publish(cloud)
        assert wait_for(lambda: len(got) == 1, 10)
        np.testing.assert_array_equal(read_xyz(got[0], ("i",)), read_xyz(cloud, ("i",)))
        time.sleep(0.3)
        assert weak.matched() == 0 and not strict  # best-effort writer never matches a reliable reader
    finally:
        a.shutdown()
        b.shutdown()


def test_local_runtime_is_a_runtime():
    from pcc_ros.runtime.base import Runtime

    assert isinstance(LocalRuntime(LocalGraph(), "n"), Runtime)
