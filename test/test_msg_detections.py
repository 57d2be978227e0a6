"""Detection3DArray / MarkerArray <-> Boxes: round trips through CDR, strict validation."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pcc_ros.errors import MessageError
from pcc_ros.msg.detections import (
    CUBE,
    DELETEALL,
    LINE_LIST,
    STATUS_COLORS,
    TEXT_VIEW_FACING,
    box_edges,
    boxes_from_detection_array,
    boxes_from_marker_array,
    detection_array_from_boxes,
    marker_array_from_boxes,
    valid_detection_mask,
)
from pcc_ros.msg.stamps import stamp_to_ns
from pcc_ros.msg.typestore import get_typestore, new_message
from pcc_ros.types import Boxes

DET = "vision_msgs/msg/Detection3DArray"
MARKERS = "visualization_msgs/msg/MarkerArray"


def cdr(msg, typename):
    store = get_typestore()
    return store.deserialize_cdr(store.serialize_cdr(msg, typename), typename)


def random_boxes(n: int, seed: int) -> Boxes:
    rng = np.random.default_rng(seed)
    return Boxes(
        rng.uniform(-40, 40, (n, 3)),
        rng.uniform(0.3, 6, (n, 3)),
        rng.uniform(-np.pi, np.pi, n),
        rng.choice(["Car", "Van", "Pedestrian"], n),
        rng.normal(0, 3, n),  # raw logits, not probabilities
        [str(i) if i % 3 else "" for i in range(n)],
    )


def detection(center=(1.0, 2.0, 0.5), quat=(0.0, 0.0, 0.0, 1.0), size=(4.0, 1.8, 1.5), hyps=(("Car", 0.9),), id=""):
    def pose():
        return new_message(
            "geometry_msgs/msg/Pose",
            position=new_message("geometry_msgs/msg/Point", x=center[0], y=center[1], z=center[2]),
            orientation=new_message("geometry_msgs/msg/Quaternion", x=quat[0], y=quat[1], z=quat[2], w=quat[3]),
        )

    results = [
        new_message(
            "vision_msgs/msg/ObjectHypothesisWithPose",
            hypothesis=new_message("vision_msgs/msg/ObjectHypothesis", class_id=c, score=s),
            pose=new_message("geometry_msgs/msg/PoseWithCovariance", pose=pose()),
        )
        for c, s in hyps
    ]
    bbox = new_message(
        "vision_msgs/msg/BoundingBox3D",
        center=pose(),
        size=new_message("geometry_msgs/msg/Vector3", x=size[0], y=size[1], z=size[2]),
    )
    return new_message("vision_msgs/msg/Detection3D", results=results, bbox=bbox, id=id)


def array_of(*detections):
    return new_message(DET, detections=list(detections))


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 12), st.integers(0, 2**31))
def test_detection_array_round_trip(n, seed):
    boxes = random_boxes(n, seed)
    msg = cdr(detection_array_from_boxes(boxes, "velodyne", 1_234_000_000_007), DET)
    assert msg.header.frame_id == "velodyne" and stamp_to_ns(msg.header.stamp) == 1_234_000_000_007
    assert len(msg.detections) == n
    assert boxes_from_detection_array(msg).equals(boxes)


def test_quaternion_is_normalised_and_yaw_extracted():
    yaw = 0.7
    q = 1.004 * np.array([0, 0, np.sin(yaw / 2), np.cos(yaw / 2)])  # float noise off unit length
    boxes = boxes_from_detection_array(array_of(detection(quat=tuple(q))))
    assert boxes.yaw[0] == pytest.approx(yaw)
    # yaw -> -yaw + 2 pi wrap, and q == -q
    boxes = boxes_from_detection_array(array_of(detection(quat=tuple(-q))))
    assert boxes.yaw[0] == pytest.approx(yaw)
    # far from unit length is not a rotation: refused, not silently normalised
    with pytest.raises(MessageError, match="quaternion norm 3 is not 1"):
        boxes_from_detection_array(array_of(detection(quat=tuple(3.0 * q / 1.004))))


def test_best_hypothesis_and_track_id():
    msg = array_of(
        detection(hyps=(("Pedestrian", 0.2), ("Car", 0.7), ("Van", 0.5)), id="track-17"),
        detection(hyps=()),
    )
    boxes = boxes_from_detection_array(cdr(msg, DET))
    assert list(boxes.label) == ["Car", ""] and list(boxes.track_id) == ["track-17", ""]
    np.testing.assert_allclose(boxes.score, [0.7, 1.0])
    np.testing.assert_allclose(boxes.size[0], [4.0, 1.8, 1.5])
    np.testing.assert_allclose(boxes.center[0], [1.0, 2.0, 0.5])


def test_empty_arrays():
    assert len(boxes_from_detection_array(array_of())) == 0
    assert valid_detection_mask(array_of()).shape == (0,)
    assert len(boxes_from_marker_array(new_message(MARKERS))) == 0
    msg = marker_array_from_boxes(Boxes.empty(), "f", 0)
    assert [m.action for m in msg.markers] == [DELETEALL]


@pytest.mark.parametrize(
    ("kwargs", "pattern"),
    [
        ({"size": (0.0, 1.8, 1.5)}, r"size \[0.0, 1.8, 1.5\] is not finite and positive"),
        ({"size": (4.0, -1.0, 1.5)}, "is not finite and positive"),
        ({"size": (4.0, 1.8, float("nan"))}, "is not finite and positive"),
        ({"center": (float("nan"), 0.0, 0.0)}, "non-finite position"),
        ({"center": (0.0, float("inf"), 0.0)}, "non-finite position"),
        ({"quat": (0.0, 0.0, 0.0, 0.0)}, "invalid orientation quaternion"),
        ({"quat": (0.0, 0.0, float("nan"), 1.0)}, "invalid orientation quaternion"),
        ({"hyps": (("Car", float("nan")),)}, "non-finite score"),
    ],
)
def test_invalid_detections_raise_and_can_be_skipped(kwargs, pattern):
    msg = array_of(detection(), detection(**kwargs))
    with pytest.raises(MessageError, match="detection 1: .*" + pattern):
        boxes_from_detection_array(msg)
    kept = boxes_from_detection_array(msg, skip_invalid=True)
    assert len(kept) == 1
    assert valid_detection_mask(msg).tolist() == [True, False]  # which originals the kept boxes came from


def test_malformed_objects():
    with pytest.raises(MessageError, match="not a Detection3DArray"):
        boxes_from_detection_array(object())
    with pytest.raises(MessageError, match="detection 0 is not a vision_msgs/Detection3D"):
        boxes_from_detection_array(new_message(DET, detections=[object()]))
    with pytest.raises(MessageError, match="not a MarkerArray"):
        boxes_from_marker_array(object())


@pytest.mark.parametrize(
    ("field", "value", "pattern"),
    [
        ("size", [[0.0, 1.0, 1.0]], "box 0: size"),
        ("size", [[1.0, 1.0, np.nan]], "box 0: size"),
        ("center", [[np.nan, 0.0, 0.0]], "box 0: non-finite position"),
        ("yaw", [np.inf], "box 0: non-finite yaw"),
        ("score", [np.nan], "box 0: non-finite score"),
    ],
)
def test_writing_invalid_boxes_raises(field, value, pattern):
    parts = {"center": [[0.0, 0.0, 0.0]], "size": [[4.0, 2.0, 1.5]], "yaw": [0.0], "score": [1.0]}
    parts[field] = value
    boxes = Boxes(parts["center"], parts["size"], parts["yaw"], score=parts["score"])
    with pytest.raises(MessageError, match=pattern):
        detection_array_from_boxes(boxes, "f", 0)
    with pytest.raises(MessageError, match=pattern):
        marker_array_from_boxes(boxes, "f", 0)


def test_marker_array_for_rviz():
    boxes = random_boxes(3, 1)
    status = np.array(["kept", "rejected", "whatever"], dtype=object)
    msg = cdr(marker_array_from_boxes(boxes, "velodyne", 99, status=status, ns="det"), MARKERS)
    markers = msg.markers
    assert markers[0].action == DELETEALL and markers[0].ns == "det"
    lines = [m for m in markers if m.type == LINE_LIST and m.action == 0]
    texts = [m for m in markers if m.type == TEXT_VIEW_FACING]
    assert len(lines) == len(texts) == 3 and not [m for m in markers if m.type == CUBE]
    assert all(m.header.frame_id == "velodyne" for m in markers)
    # colour by status, unknown status gets a colour too
    assert (lines[0].color.r, lines[0].color.g) == pytest.approx(STATUS_COLORS["kept"][:2])
    assert (lines[1].color.r, lines[1].color.g) == pytest.approx(STATUS_COLORS["rejected"][:2])
    assert lines[2].color.a == 1.0
    # edges: 12 box edges + front cross; every end point lies on the box surface
    points = np.array([[p.x, p.y, p.z] for p in lines[0].points])
    assert len(points) == 28
    np.testing.assert_allclose(points, box_edges(boxes[0])[0])
    local = points - boxes.center[0]
    c, s = np.cos(-boxes.yaw[0]), np.sin(-boxes.yaw[0])
    local = np.stack([c * local[:, 0] - s * local[:, 1], s * local[:, 0] + c * local[:, 1], local[:, 2]], 1)
    np.testing.assert_allclose(np.abs(local), np.broadcast_to(boxes.size[0] / 2, local.shape), atol=1e-9)
    # text: class and score, above the box
    assert texts[1].text == f"{boxes.label[1]} {boxes.score[1]:.2f}"
    assert texts[1].pose.position.z > boxes.center[1, 2] + boxes.size[1, 2] / 2


def test_status_length_must_match():
    with pytest.raises(MessageError, match="status has 1 entries for 3 boxes"):
        marker_array_from_boxes(random_boxes(3, 0), "f", 0, status=["kept"])


def test_cube_markers_round_trip():
    boxes = random_boxes(5, 2)
    msg = cdr(marker_array_from_boxes(boxes, "lidar", 0, cubes=True), MARKERS)
    back = boxes_from_marker_array(msg)  # lines / text / DELETEALL are ignored
    assert len(back) == 5
    np.testing.assert_allclose(back.center, boxes.center)
    np.testing.assert_allclose(back.size, boxes.size)
    np.testing.assert_allclose(np.angle(np.exp(1j * (back.yaw - boxes.yaw))), 0, atol=1e-9)
    assert list(back.label) == list(boxes.label)
    assert list(back.track_id) == [str(i) for i in range(5)]


def _cube(frame="lidar", scale=(4.0, 2.0, 1.5), quat=(0, 0, 0, 1), ns="car", text=""):
    return new_message(
        "visualization_msgs/msg/Marker",
        header=new_message("std_msgs/msg/Header", frame_id=frame),
        ns=ns,
        id=3,
        type=CUBE,
        action=0,
        pose=new_message(
            "geometry_msgs/msg/Pose",
            position=new_message("geometry_msgs/msg/Point", x=1.0, y=2.0, z=3.0),
            orientation=new_message("geometry_msgs/msg/Quaternion", x=quat[0], y=quat[1], z=quat[2], w=quat[3]),
        ),
        scale=new_message("geometry_msgs/msg/Vector3", x=scale[0], y=scale[1], z=scale[2]),
        text=text,
    )


def test_cube_marker_reading_and_errors():
    boxes = boxes_from_marker_array(new_message(MARKERS, markers=[_cube(), _cube(text="Van")]))
    assert list(boxes.label) == ["car", "Van"] and list(boxes.track_id) == ["3", "3"]
    with pytest.raises(MessageError, match="different frames"):
        boxes_from_marker_array(new_message(MARKERS, markers=[_cube(), _cube(frame="map")]))
    with pytest.raises(MessageError, match="cube marker 1: size"):
        boxes_from_marker_array(new_message(MARKERS, markers=[_cube(), _cube(scale=(0.0, 1.0, 1.0))]))
    with pytest.raises(MessageError, match="cube marker 0: invalid orientation"):
        boxes_from_marker_array(new_message(MARKERS, markers=[_cube(quat=(0, 0, 0, 0))]))
    assert (
        len(boxes_from_marker_array(new_message(MARKERS, markers=[_cube(quat=(0, 0, 0, 0))]), skip_invalid=True)) == 0
    )


def test_markers_of_one_array_do_not_share_their_lists():
    """The markers are copies of per-kind templates: appending to one marker's points (or
    colours) changes that marker only."""
    from pcc_ros.msg.detections import marker_array_from_boxes

    boxes = Boxes(np.array([[5.0, 0, 0], [9.0, 2, 0]]), np.array([[4.0, 1.8, 1.5]] * 2), np.zeros(2),
                  label=["Car", "Car"], score=[0.9, 0.4])
    markers = marker_array_from_boxes(boxes, "velodyne", 1, cubes=True).markers
    texts = [m for m in markers if m.ns == "boxes_text"]
    texts[0].points.append(markers[1].points[0])
    texts[0].colors.append(markers[1].color)
    assert [len(m.points) for m in texts] == [1, 0] and [len(m.colors) for m in texts] == [1, 0]
    lines = [m for m in markers if m.ns == "boxes"][1:]
    assert lines[0].points is not lines[1].points and len(lines[0].points) == len(lines[1].points) > 0
