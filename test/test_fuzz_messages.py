"""Fuzz corpus, messages: hostile Detection3DArrays and PointCloud2s through the decoders and
the pipeline the nodes run — every problem is a counted, logged skip naming the detection,
or a MessageError for the frame; the work per frame stays bounded."""

from __future__ import annotations

import logging

import numpy as np
import pytest
from fuzz_support import CAR, car_points
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_msg_detections import array_of, detection

from pcc_ros.errors import MessageError
from pcc_ros.geometry.boxes import BoxCandidates, points_in_boxes
from pcc_ros.msg import detections as detections_module
from pcc_ros.msg.detections import DEFAULT_LIMITS, decode_detection_array
from pcc_ros.msg.pointcloud2 import FLOAT32, INT16, create_cloud, read_xyz
from pcc_ros.msg.typestore import new_message
from pcc_ros.pipeline.core import Pipeline, PipelineConfig

STAMP = 1_700_000_000_000_000_000


def quat_of(roll: float, pitch: float, yaw: float) -> tuple[float, float, float, float]:
    from scipy.spatial.transform import Rotation

    return tuple(Rotation.from_euler("xyz", [roll, pitch, yaw]).as_quat())


def scan(n: int = 3000, seed: int = 0):
    rng = np.random.default_rng(seed)
    pts = np.concatenate([np.c_[rng.uniform(-30, 30, (n, 2)), rng.uniform(-1, 0, n)], car_points(rng)])
    return create_cloud(pts.astype(np.float32), ["x", "y", "z"], "velodyne", STAMP)


def stamped(msg, stamp_ns: int = STAMP, frame: str = "velodyne"):
    from pcc_ros.msg.stamps import make_header

    msg.header = make_header(frame, stamp_ns)
    return msg


@pytest.fixture(scope="module")
def pipeline():
    return Pipeline(PipelineConfig(backend="mirror", min_points=10))


_FLOATS = st.one_of(st.floats(-50, 50), st.sampled_from([np.nan, np.inf, -np.inf, 1e30, -1e30, 0.0, -1.0, 1e-12]))


@st.composite
def hostile_detection(draw):
    center = tuple(draw(_FLOATS) for _ in range(3))
    size = tuple(draw(st.one_of(st.floats(0.1, 8), _FLOATS)) for _ in range(3))
    quat = draw(st.one_of(
        st.tuples(st.floats(-np.pi / 2, np.pi / 2), st.floats(-np.pi / 2, np.pi / 2), st.floats(-4, 4))
        .map(lambda e: quat_of(*e)),
        st.tuples(_FLOATS, _FLOATS, _FLOATS, _FLOATS),
    ))
    score = draw(st.one_of(st.floats(0, 1), _FLOATS))
    ident = draw(st.text("ab0123", max_size=4))
    return detection(center=center, quat=quat, size=size, hyps=(("Car", score),), id=ident)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(dets=st.lists(hostile_detection(), max_size=8))
def test_hostile_detections_are_skipped_per_detection(dets, caplog):
    caplog.clear()
    detections_module._skipped[0] = 0  # each example as a fresh process: its skips logged one by one
    with caplog.at_level(logging.WARNING):
        boxes, keep = decode_detection_array(array_of(*dets), skip_invalid=True)
    assert len(boxes) == int(keep.sum()) and len(keep) == len(dets)
    assert np.isfinite(boxes.center).all() and np.isfinite(boxes.yaw).all() and np.isfinite(boxes.score).all()
    assert ((boxes.size > 0) & (boxes.size <= DEFAULT_LIMITS.max_size)).all()
    assert (np.abs(boxes.center) <= DEFAULT_LIMITS.max_range).all()
    skipped = [i for i, k in enumerate(keep) if not k]
    for i in skipped[:5]:  # each skip logged with its index and id
        name = f"detection {i}" + (f" (id {dets[i].id!r})" if dets[i].id else "")
        assert f"skipped {name}:" in caplog.text


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(dets=st.lists(hostile_detection(), max_size=6))
def test_pipeline_survives_hostile_detections(pipeline, dets):
    msg = stamped(array_of(*dets))
    result, originals = pipeline.process_messages(scan(), msg)
    valid = decode_detection_array(msg, skip_invalid=True)[1]
    assert len(result.detections) == len(originals) == int(valid.sum())
    assert result.skipped.get("invalid detection", 0) == int((~valid).sum())
    assert np.isfinite(result.completed_points).all()


def test_huge_box_is_skipped_naming_the_detection(pipeline, caplog):
    msg = stamped(array_of(detection(size=(1e30, 1e30, 1e30), id="truck-9"),
                           detection(center=CAR["center"], size=CAR["size"], id="car-1")))
    with caplog.at_level(logging.WARNING):
        result, _ = pipeline.process_messages(scan(), msg)
    assert "detection 0 (id 'truck-9'): size [1e+30, 1e+30, 1e+30] exceeds max_box_size 40 m" in caplog.text
    assert result.skipped["invalid detection"] == 1 and list(result.detections.track_id) == ["car-1"]


def test_quaternions_normalised_or_refused_and_tilt_explicit(caplog):
    yaw = 0.4
    small_tilt = quat_of(0.1, 0.0, yaw)  # 6 degrees of roll: dropped, heading kept
    large_tilt = quat_of(0.0, 0.6, yaw)  # 34 degrees of pitch: refused
    scaled = tuple(1.5 * np.array(quat_of(0, 0, yaw)))  # not a rotation: refused
    msg = array_of(detection(quat=small_tilt, id="a"), detection(quat=large_tilt, id="b"),
                   detection(quat=scaled, id="c"))
    with caplog.at_level(logging.WARNING):
        boxes, keep = decode_detection_array(msg, skip_invalid=True)
    assert keep.tolist() == [True, False, False]
    assert boxes.yaw[0] == pytest.approx(yaw, abs=1e-6)
    assert "detection 1 (id 'b'): roll / pitch tilt 34.4 deg exceeds max_box_tilt" in caplog.text
    assert "detection 2 (id 'c'): quaternion norm 1.5 is not 1" in caplog.text


def test_negative_stamps_are_refused(pipeline):
    with pytest.raises(MessageError, match="negative"):
        pipeline.process_messages(scan(), stamped(array_of(detection()), stamp_ns=-5))
    cloud = scan()
    cloud.header.stamp.sec = -1
    with pytest.raises(MessageError, match=r"scan stamp .* is negative"):
        pipeline.process_messages(cloud, stamped(array_of(detection())))


def test_work_bound_skips_lowest_scores_and_counts(caplog):
    config = PipelineConfig(backend="mirror", min_points=10, max_instances=500, max_crop_work=20_000)
    pipe = Pipeline(config)
    dense = scan(n=40_000)
    rng = np.random.default_rng(0)
    xys = zip(rng.uniform(-5, 5, 200), rng.uniform(-5, 5, 200), rng.uniform(0, 1, 200))
    dets = [detection(center=(float(x), float(y), 0.0), size=(39.0, 39.0, 5.0), hyps=(("Car", float(s)),), id=str(i))
            for i, (x, y, s) in enumerate(xys)]
    with caplog.at_level(logging.WARNING):
        result, _ = pipe.process_messages(dense, stamped(array_of(*dets)))
    over = result.skipped["over max_crop_work"]
    assert 150 < over <= 200 and "exceed max_crop_work 20000" in caplog.text
    completed = result.completed_index
    if len(completed):  # the completed ones are the highest-scoring boxes
        assert result.detections.score[completed].min() >= np.sort(result.detections.score)[-(200 - over)]
    # the scan evidence judges more (its bound is 10x the crop's), the rest marked unjudged
    judged = np.isin(result.status, ("kept", "rejected"))
    unjudged = result.status == "unjudged"
    assert judged.sum() >= 200 - over and judged.sum() + unjudged.sum() == 200
    assert unjudged.sum() == result.skipped.get("unjudged over evidence work", 0)
    if unjudged.any():
        assert result.detections.score[judged].min() >= result.detections.score[unjudged].max()


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31), n=st.integers(1, 30), margin=st.floats(0, 1))
def test_work_estimate_bounds_the_real_crop(seed, n, margin):
    from pcc_ros.types import Boxes

    rng = np.random.default_rng(seed)
    points = rng.uniform(-40, 40, (5000, 3)).astype(np.float32)
    boxes = Boxes(rng.uniform(-45, 45, (n, 3)), rng.uniform(0.1, 30, (n, 3)), rng.uniform(-4, 4, n))
    real = np.array([len(i) for i in points_in_boxes(points, boxes, margin)])
    assert (BoxCandidates(points, boxes, margin).pairs_per_box >= real).all()


# ----------------------------------------------------------------------------- PointCloud2


def test_integer_and_overlapping_xyz_are_refused():
    def cloud(fields, point_step=12):
        return new_message("sensor_msgs/msg/PointCloud2", height=1, width=2, point_step=point_step,
                           row_step=2 * point_step, is_dense=True, data=np.zeros(2 * point_step, np.uint8),
                           fields=[new_message("sensor_msgs/msg/PointField", name=n, offset=o, datatype=d, count=1)
                                   for n, o, d in fields])

    with pytest.raises(MessageError, match="'x' is INT16; x, y, z must be FLOAT32 or FLOAT64"):
        read_xyz(cloud([("x", 0, INT16), ("y", 4, FLOAT32), ("z", 8, FLOAT32)]))
    with pytest.raises(MessageError, match="fields 'x' and 'y' overlap"):
        read_xyz(cloud([("x", 0, FLOAT32), ("y", 2, FLOAT32), ("z", 8, FLOAT32)]))


@st.composite
def hostile_cloud(draw):
    fields = [new_message("sensor_msgs/msg/PointField", name=draw(st.sampled_from(["x", "y", "z", "i", ""])),
                          offset=draw(st.integers(-2, 20)), datatype=draw(st.integers(0, 9)),
                          count=draw(st.integers(0, 3)))
              for _ in range(draw(st.integers(0, 5)))]
    height, width = draw(st.integers(0, 3)), draw(st.integers(0, 5))
    point_step = draw(st.integers(0, 24))
    row_step = draw(st.one_of(st.just(point_step * width), st.integers(0, 130)))
    size = draw(st.one_of(st.just(row_step * height), st.integers(0, 400)))
    data = np.frombuffer(draw(st.binary(min_size=size, max_size=size)), np.uint8)
    return new_message("sensor_msgs/msg/PointCloud2", height=height, width=width, fields=fields,
                       is_bigendian=draw(st.booleans()), point_step=point_step, row_step=row_step, data=data,
                       is_dense=False)


@settings(max_examples=300, deadline=None)
@given(msg=hostile_cloud())
def test_hostile_clouds_decode_or_raise_a_message_error(msg):
    try:
        xyz = read_xyz(msg)
    except MessageError:
        return
    assert xyz.dtype == np.float32 and xyz.shape[1] == 3 and np.isfinite(xyz).all()
    assert len(xyz) <= msg.height * msg.width
