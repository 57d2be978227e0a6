"""3D boxes <-> ``vision_msgs/Detection3DArray`` and ``visualization_msgs/MarkerArray``.

The package's box is :class:`~pcc_ros.types.Boxes` (centre, size = length / width / height,
yaw about +z). vision_msgs 4.x stores a full 6-DoF pose plus a list of class hypotheses;
the conversion keeps:

* centre = ``bbox.center.position``; size = ``bbox.size`` (x = length along the heading,
  y = width, z = height); yaw = heading of the box's x axis after rotating by the
  normalised ``bbox.center.orientation`` (roll / pitch, rare for road vehicles, are
  dropped);
* label / score = the hypothesis with the highest score (``""`` / ``1.0`` when a detection
  has no hypotheses: Boxes' convention for an unscored box);
* ``Detection3D.id`` = ``Boxes.track_id``.

Reading is strict: a NaN / inf pose, a zero-length or non-finite quaternion, a size that is
not finite and positive, or a non-finite score raises :class:`MessageError` naming the
detection (``skip_invalid=True`` instead drops those boxes and logs each one with its
index and ``id``). Writing validates the boxes the same way. :class:`DetectionLimits`
adds plausibility bounds, all configurable (the pipeline takes them from its parameters):

* sizes above ``max_size`` metres and positions beyond ``max_range`` metres are refused
  (a 1e30 m box would otherwise overflow the crop's grid arithmetic);
* a quaternion whose norm is off 1 by more than ``quaternion_tolerance`` is refused (not a
  rotation: some bug upstream); within the tolerance it is normalised;
* roll / pitch: the box's z axis may tilt from vertical by at most ``max_tilt`` radians —
  the tilt is then dropped and the heading kept; a more tilted box is refused, since a
  yaw-only box would crop the wrong points;
* ``score_range``: with ``score_mapping: identity`` scores are probabilities, and a score
  outside [0, 1] (a logit?) is refused with a hint.

:func:`marker_array_from_boxes` draws boxes for RViz: a ``DELETEALL`` first (stale boxes of
the previous frame disappear), one ``LINE_LIST`` per box (12 edges plus a cross on the
front face to show the heading) coloured by status, and a ``TEXT_VIEW_FACING`` label with
class and score above each box.
"""

from __future__ import annotations

import copy
import logging
import threading
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from pcc_ros.errors import ConfigError, MessageError
from pcc_ros.geometry.boxes import box_corners
from pcc_ros.geometry.rotations import (
    quaternion_from_yaw,
    quaternion_product,
    tilt_from_quaternion,
    yaw_from_quaternion,
)
from pcc_ros.geometry.transforms import Transform
from pcc_ros.lograte import worth_logging
from pcc_ros.msg.stamps import make_header
from pcc_ros.msg.typestore import ClassResolver, from_template, new_message, resolve
from pcc_ros.types import Boxes

log = logging.getLogger(__name__)

# visualization_msgs/Marker constants (identical in rclpy and rosbags classes).
ARROW, CUBE, LINE_LIST, TEXT_VIEW_FACING = 0, 1, 5, 9
ADD, DELETE, DELETEALL = 0, 2, 3

#: RGBA per status for :func:`marker_array_from_boxes`; unknown statuses are white.
STATUS_COLORS: dict[str | None, tuple[float, float, float, float]] = {
    None: (0.0, 0.8, 1.0, 1.0),  # no status given: cyan
    "kept": (0.1, 0.9, 0.2, 1.0),  # green
    "rejected": (1.0, 0.15, 0.1, 1.0),  # red
    "completed": (0.2, 0.4, 1.0, 1.0),  # blue
    "skipped": (0.6, 0.6, 0.6, 1.0),  # grey: too few points, wrong class ...
    "unjudged": (1.0, 0.8, 0.0, 1.0),  # amber: a filtered class the filter could not judge
}
_OTHER_COLOR = (1.0, 1.0, 1.0, 1.0)

# Line segments drawn per box, as corner indices of :func:`pcc_ros.geometry.boxes.box_corners`
# (0-3 bottom face counter-clockwise from front-left: FL, RL, RR, FR; 4-7 the top face alike):
# bottom ring, top ring, verticals, then an X across the front face (corners 0, 3, 4, 7).
_EDGES = np.array(
    [[0, 3], [3, 2], [2, 1], [1, 0], [4, 7], [7, 6], [6, 5], [5, 4], [0, 4], [3, 7], [2, 6], [1, 5], [0, 7], [3, 4]]
)


@dataclass(frozen=True)
class DetectionLimits:
    """Plausibility bounds for incoming boxes (see the module docstring)."""

    max_size: float = 40.0  # metres, any of length / width / height (articulated buses, trams)
    max_range: float = 1000.0  # metres, |centre coordinate|
    quaternion_tolerance: float = 0.01  # allowed | |q| - 1 |
    max_tilt: float = 0.35  # radians (20 degrees) of roll / pitch
    score_range: tuple[float, float] | None = None  # e.g. (0, 1) for probabilities

    def __post_init__(self) -> None:
        if not (self.max_size > 0 and self.max_range > 0 and self.quaternion_tolerance >= 0
                and 0 <= self.max_tilt <= np.pi):
            raise ConfigError("max_box_size and max_box_range must be > 0, max_box_tilt in [0, pi]")


#: Bounds used when a caller passes none.
DEFAULT_LIMITS = DetectionLimits()
#: At most this many skipped detections are logged one by one per message; the rest are counted.
_LOGGED_PER_MESSAGE = 5
#: The first this many skipped boxes of a process are logged one by one; after that one line at
#: every power of ten (a detector that sends a degenerate box in every frame must not flood a
#: node's log at the scan rate; the callers count every skip per frame).
_LOGGED_IN_FULL = 20
_skipped = [0]  # invalid boxes skipped by this process so far
_skipped_lock = threading.Lock()


def _invalid_reasons(
    center: np.ndarray, size: np.ndarray, quat: np.ndarray | None, score: np.ndarray,
    limits: DetectionLimits | None = None,
) -> list[str]:
    """Per box, ``""`` if valid, else what is wrong (vectorised checks, strings only for bad rows)."""
    with np.errstate(invalid="ignore", over="ignore"):
        bad_center = ~np.isfinite(center).all(axis=1)
        bad_size = ~(np.isfinite(size).all(axis=1) & (size > 0).all(axis=1))
        bad_score = ~np.isfinite(score)
        far = big = bad_norm = tilted = off_range = np.zeros(len(center), dtype=bool)
        if quat is not None:
            norm = np.linalg.norm(quat, axis=1)
            bad_quat = ~np.isfinite(quat).all(axis=1) | ~(norm > 1e-9)
        else:
            bad_quat = np.zeros(len(center), dtype=bool)
        if limits is not None:
            far = ~bad_center & (np.abs(center) > limits.max_range).any(axis=1)
            big = ~bad_size & (size > limits.max_size).any(axis=1)
            if quat is not None:
                bad_norm = ~bad_quat & (np.abs(norm - 1.0) > limits.quaternion_tolerance)
                unit = quat / np.where(bad_quat, 1.0, norm)[:, None]
                tilt = tilt_from_quaternion(unit)
                tilted = ~bad_quat & ~bad_norm & (tilt > limits.max_tilt)
            if limits.score_range is not None:
                lo, hi = limits.score_range
                off_range = ~bad_score & ((score < lo) | (score > hi))
    reasons = [""] * len(center)
    for i in np.flatnonzero(bad_center | bad_size | bad_score | bad_quat | far | big | bad_norm | tilted | off_range):
        parts = []
        if bad_center[i]:
            parts.append(f"non-finite position {center[i].tolist()}")
        if far[i]:
            parts.append(f"position {center[i].tolist()} beyond max_box_range {limits.max_range:g} m")
        if bad_quat[i]:
            parts.append(f"invalid orientation quaternion {quat[i].tolist()}")
        if bad_norm[i]:
            parts.append(f"quaternion norm {norm[i]:.6g} is not 1 (tolerance {limits.quaternion_tolerance:g})")
        if tilted[i]:
            parts.append(f"roll / pitch tilt {np.degrees(tilt[i]):.1f} deg exceeds max_box_tilt "
                         f"{np.degrees(limits.max_tilt):.1f} deg (boxes are yaw-only)")
        if bad_size[i]:
            parts.append(f"size {size[i].tolist()} is not finite and positive")
        if big[i]:
            parts.append(f"size {size[i].tolist()} exceeds max_box_size {limits.max_size:g} m")
        if bad_score[i]:
            parts.append(f"non-finite score {score[i]}")
        if off_range[i]:
            parts.append(f"score {score[i]:g} outside {list(limits.score_range)} "
                         "(score_mapping identity expects probabilities; use sigmoid for logits)")
        reasons[i] = ", ".join(parts)
    return reasons


def _keep_valid(reasons: list[str], what: str, skip_invalid: bool, ids: np.ndarray | None = None) -> np.ndarray:
    bad = [i for i, r in enumerate(reasons) if r]

    def name(i: int) -> str:
        return f"{what} {i}" + (f" (id {str(ids[i])!r})" if ids is not None and str(ids[i]) else "")

    if bad and not skip_invalid:
        more = f" (and {len(bad) - 1} more)" if len(bad) > 1 else ""
        raise MessageError(f"{name(bad[0])}: {reasons[bad[0]]}{more}")
    with _skipped_lock:
        before = _skipped[0]
        _skipped[0] += len(bad)
    in_full = 0  # this message's boxes logged one by one
    for j, i in enumerate(bad):
        total = before + j + 1
        if total <= _LOGGED_IN_FULL and j < _LOGGED_PER_MESSAGE:
            log.warning("skipped %s: %s", name(i), reasons[i])
            in_full += 1
        elif total > _LOGGED_IN_FULL and worth_logging(total):  # 100, 1000, ...
            log.warning("skipped %s: %s (%d invalid boxes skipped so far; logged one by one for the first %d, "
                        "from here at every power of ten)", name(i), reasons[i], total, _LOGGED_IN_FULL)
    if in_full and len(bad) > in_full:
        log.warning("skipped %d more invalid %ss in this message", len(bad) - in_full, what)
    keep = np.ones(len(reasons), dtype=bool)
    keep[bad] = False
    return keep


#: class_id prefix of the detection filter's annotations (``pcc_filter_score``,
#: ``pcc_filter/<term>``): never a detection's class (docs/filter.md).
FILTER_HYPOTHESIS_PREFIX = "pcc_filter"


def _best_hypothesis(results) -> tuple[str, float]:
    best_label, best_score = "", None
    for result in results:  # a handful of hypotheses per detection
        if str(result.hypothesis.class_id).startswith(FILTER_HYPOTHESIS_PREFIX):
            continue
        score = float(result.hypothesis.score)
        if best_score is None or score > best_score or (np.isnan(score) and not np.isnan(best_score)):
            best_label, best_score = str(result.hypothesis.class_id), score
    return best_label, 1.0 if best_score is None else best_score


def _detection_arrays(msg) -> tuple[np.ndarray, ...] | None:
    """(center, quaternion, size, label, score, track id) arrays of a Detection3DArray, or None if empty."""
    try:
        detections = list(msg.detections)
    except (AttributeError, TypeError):
        raise MessageError("object is not a Detection3DArray (no 'detections')") from None
    if not detections:
        return None
    center, quat, size, label, score, track = [], [], [], [], [], []
    for i, det in enumerate(detections):
        try:
            pose, dims = det.bbox.center, det.bbox.size
            center.append((pose.position.x, pose.position.y, pose.position.z))
            o = pose.orientation
            quat.append((o.x, o.y, o.z, o.w))
            size.append((dims.x, dims.y, dims.z))
            best = _best_hypothesis(det.results)
            label.append(best[0])
            score.append(best[1])
            track.append(str(det.id))
        except (AttributeError, TypeError, ValueError) as exc:
            raise MessageError(f"detection {i} is not a vision_msgs/Detection3D ({exc})") from None
    return (
        np.asarray(center, dtype=np.float64),
        np.asarray(quat, dtype=np.float64),
        np.asarray(size, dtype=np.float64),
        np.asarray(label, dtype=object),
        np.asarray(score, dtype=np.float64),
        np.asarray(track, dtype=object),
    )


def valid_detection_mask(msg, limits: DetectionLimits | None = DEFAULT_LIMITS) -> np.ndarray:
    """Which entries of ``msg.detections`` :func:`boxes_from_detection_array` keeps with
    ``skip_invalid=True`` — so a caller can republish the original messages of the valid boxes."""
    arrays = _detection_arrays(msg)
    if arrays is None:
        return np.zeros(0, dtype=bool)
    center, quat, size, _, score, _ = arrays
    return np.array([not r for r in _invalid_reasons(center, size, quat, score, limits)], dtype=bool)


def decode_detection_array(
    msg, skip_invalid: bool = False, limits: DetectionLimits | None = DEFAULT_LIMITS,
    transform: Transform | None = None,
) -> tuple[Boxes, np.ndarray]:
    """:class:`Boxes` of a ``vision_msgs/Detection3DArray`` and which entries of
    ``msg.detections`` they came from (one decode for callers that republish the originals).

    ``transform`` (``scan frame <- detections' frame``, as tf2 gives it) moves every pose
    once, before the checks: the limits (range, tilt) apply in the frame the boxes are used
    in, and the yaw is the heading of the moved orientation (no re-encoding, nothing lost).
    """
    arrays = _detection_arrays(msg)
    if arrays is None:
        return Boxes.empty(), np.zeros(0, dtype=bool)
    center_a, quat_a, size_a, label_a, score_a, track_a = arrays
    if transform is not None:
        matrix = transform.matrix()
        center_a = center_a @ matrix[:3, :3].T + matrix[:3, 3]
        turn = np.asarray(transform.rotation, dtype=np.float64)
        quat_a = np.stack(quaternion_product(turn / np.linalg.norm(turn), quat_a.T), axis=1)
    reasons = _invalid_reasons(center_a, size_a, quat_a, score_a, limits)
    keep = _keep_valid(reasons, "detection", skip_invalid, track_a)
    quat_a = quat_a[keep] / np.linalg.norm(quat_a[keep], axis=1, keepdims=True)
    boxes = Boxes(
        center_a[keep],
        size_a[keep],
        yaw_from_quaternion(quat_a),
        label_a[keep],
        score_a[keep],
        track_a[keep],
    )
    return boxes, keep


def boxes_from_detection_array(
    msg, skip_invalid: bool = False, limits: DetectionLimits | None = DEFAULT_LIMITS
) -> Boxes:
    """:class:`Boxes` from a ``vision_msgs/Detection3DArray`` (see the module docstring)."""
    return decode_detection_array(msg, skip_invalid, limits)[0]


def transform_detections(detections: Sequence, transform: Transform, frame: str) -> list:
    """Copies of ``vision_msgs/Detection3D`` messages (any class flavour) expressed in ``frame``:
    box and hypothesis poses moved by ``transform`` (``frame <- their frame``), each
    hypothesis's pose covariance rotated with it; ids, labels, scores and sizes untouched."""
    matrix = transform.matrix()
    rotation, translation = matrix[:3, :3], matrix[:3, 3]
    turn = np.asarray(transform.rotation, dtype=np.float64)
    turn = turn / np.linalg.norm(turn)
    both = np.zeros((6, 6))
    both[:3, :3] = both[3:, 3:] = rotation  # position and rotation-vector blocks turn alike

    def move(pose) -> None:
        p, o = pose.position, pose.orientation
        x, y, z = rotation @ (p.x, p.y, p.z) + translation
        p.x, p.y, p.z = float(x), float(y), float(z)
        o.x, o.y, o.z, o.w = (float(v) for v in quaternion_product(turn, (o.x, o.y, o.z, o.w)))

    out = []
    for detection in detections:
        moved = copy.deepcopy(detection)
        moved.header.frame_id = frame
        move(moved.bbox.center)
        for result in moved.results:
            move(result.pose.pose)
            covariance = np.asarray(result.pose.covariance, dtype=np.float64).reshape(6, 6)
            if covariance.any():
                result.pose.covariance = (both @ covariance @ both.T).reshape(36)
        out.append(moved)
    return out


def _check_boxes(boxes: Boxes) -> None:
    _keep_valid(_invalid_reasons(boxes.center, boxes.size, None, boxes.score), "box", skip_invalid=False)
    if not np.isfinite(boxes.yaw).all():
        raise MessageError(f"box {int(np.flatnonzero(~np.isfinite(boxes.yaw))[0])}: non-finite yaw")


_NO_ROTATION = {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}


def _pose(classes, center, yaw):
    return new_message(
        "geometry_msgs/msg/Pose",
        classes,
        position=new_message(
            "geometry_msgs/msg/Point", classes, x=float(center[0]), y=float(center[1]), z=float(center[2])
        ),
        orientation=new_message(  # the markers' upright poses (yaw 0) skip the numpy round trip: same values
            "geometry_msgs/msg/Quaternion", classes,
            **(_NO_ROTATION if yaw == 0.0 else dict(zip("xyzw", quaternion_from_yaw(yaw).tolist()))),
        ),
    )


def _vector3(classes, v):
    return new_message("geometry_msgs/msg/Vector3", classes, x=float(v[0]), y=float(v[1]), z=float(v[2]))


def detection_array_from_boxes(boxes: Boxes, frame_id: str, stamp_ns: int, classes: ClassResolver | None = None):
    """A ``vision_msgs/msg/Detection3DArray``: one detection per box, one hypothesis
    (label, score) whose pose equals the box pose, ``id`` = track id."""
    _check_boxes(boxes)
    header = make_header(frame_id, stamp_ns, classes)
    detections = []
    for i in range(len(boxes)):
        hypothesis = new_message(
            "vision_msgs/msg/ObjectHypothesisWithPose",
            classes,
            hypothesis=new_message(
                "vision_msgs/msg/ObjectHypothesis", classes, class_id=str(boxes.label[i]), score=float(boxes.score[i])
            ),
            pose=new_message(
                "geometry_msgs/msg/PoseWithCovariance",
                classes,
                pose=_pose(classes, boxes.center[i], boxes.yaw[i]),
                covariance=np.zeros(36, dtype=np.float64),
            ),
        )
        detections.append(
            new_message(
                "vision_msgs/msg/Detection3D",
                classes,
                header=make_header(frame_id, stamp_ns, classes),
                results=[hypothesis],
                bbox=new_message(
                    "vision_msgs/msg/BoundingBox3D",
                    classes,
                    center=_pose(classes, boxes.center[i], boxes.yaw[i]),
                    size=_vector3(classes, boxes.size[i]),
                ),
                id=str(boxes.track_id[i]),
            )
        )
    return new_message("vision_msgs/msg/Detection3DArray", classes, header=header, detections=detections)


def boxes_from_marker_array(msg, skip_invalid: bool = False) -> Boxes:
    """:class:`Boxes` from the ``CUBE`` markers (action ADD) of a ``visualization_msgs/MarkerArray``.

    Older detector wrappers publish boxes this way. Size = ``scale``, label = ``text`` if set,
    else ``ns``; track id = ``str(id)``; score = 1.0 (markers carry none). Other marker types
    (lines, text, DELETE / DELETEALL) are not boxes and are ignored. All cubes must share one
    ``header.frame_id``: Boxes carry no frame, so mixing frames would silently misplace boxes.
    """
    try:
        markers = list(msg.markers)
        cubes = [m for m in markers if int(m.type) == CUBE and int(m.action) == ADD]
    except (AttributeError, TypeError, ValueError):
        raise MessageError("object is not a MarkerArray of visualization_msgs/Marker") from None
    if not cubes:
        return Boxes.empty()
    center, quat, size, label, track, frames = [], [], [], [], [], set()
    for i, m in enumerate(cubes):
        try:
            p, o, s = m.pose.position, m.pose.orientation, m.scale
            center.append((p.x, p.y, p.z))
            quat.append((o.x, o.y, o.z, o.w))
            size.append((s.x, s.y, s.z))
            label.append(str(m.text) or str(m.ns))
            track.append(str(int(m.id)))
            frames.add(str(m.header.frame_id))
        except (AttributeError, TypeError, ValueError) as exc:
            raise MessageError(f"cube marker {i} is malformed ({exc})") from None
    if len(frames) > 1:
        raise MessageError(f"CUBE markers are in different frames {sorted(frames)}")
    center_a = np.asarray(center, dtype=np.float64)
    quat_a = np.asarray(quat, dtype=np.float64)
    size_a = np.asarray(size, dtype=np.float64)
    score_a = np.ones(len(cubes))
    reasons = _invalid_reasons(center_a, size_a, quat_a, score_a, DEFAULT_LIMITS)
    keep = _keep_valid(reasons, "cube marker", skip_invalid)
    quat_a = quat_a[keep] / np.linalg.norm(quat_a[keep], axis=1, keepdims=True)
    return Boxes(
        center_a[keep],
        size_a[keep],
        yaw_from_quaternion(quat_a),
        np.asarray(label, dtype=object)[keep],
        score_a[keep],
        np.asarray(track, dtype=object)[keep],
    )


def box_edges(boxes: Boxes) -> np.ndarray:
    """``(N, 2 * len(_EDGES), 3)`` line-segment end points (12 edges + front cross) per box."""
    return box_corners(boxes)[:, _EDGES.reshape(-1)]


def box_edge_points(boxes: Boxes, classes: ClassResolver | None = None) -> list[list]:
    """Per box, the ``geometry_msgs/Point`` list of its :func:`box_edges` (a ``LINE_LIST``),
    built once so several marker arrays of the same boxes can share it (``edge_points``)."""
    point_cls = resolve(classes)("geometry_msgs/msg/Point")  # x, y, z given: no defaults to fill
    return [[point_cls(x=x, y=y, z=z) for x, y, z in box] for box in box_edges(boxes).tolist()]


def _color(classes, rgba):
    return new_message("std_msgs/msg/ColorRGBA", classes, r=rgba[0], g=rgba[1], b=rgba[2], a=rgba[3])


#: The list fields of ``visualization_msgs/msg/Marker`` (each marker gets its own).
_MARKER_LISTS = ("points", "colors", "uv_coordinates")


def marker_array_from_boxes(
    boxes: Boxes,
    frame_id: str,
    stamp_ns: int,
    status: Sequence[str] | np.ndarray | None = None,
    ns: str = "boxes",
    classes: ClassResolver | None = None,
    cubes: bool = False,
    line_width: float = 0.08,
    text_height: float = 0.6,
    texts: Sequence[str] | None = None,
    edge_points: list[list] | None = None,
):
    """A ``visualization_msgs/msg/MarkerArray`` drawing ``boxes`` for RViz.

    Markers, in order: ``DELETEALL`` (namespace ``ns``); per box ``i`` a ``LINE_LIST``
    (``ns``, id ``i``) coloured by ``status[i]`` (:data:`STATUS_COLORS`), a
    ``TEXT_VIEW_FACING`` (``ns + "_text"``, id ``i``) reading ``texts[i]`` (default
    ``"<label> <score>"``) above the box and, with ``cubes=True``, a translucent ``CUBE``
    (``ns + "_cubes"``, id ``i``, text = label) that :func:`boxes_from_marker_array` can read back.
    ``edge_points``: :func:`box_edge_points` of ``boxes``, when the caller draws the same boxes
    more than once (the point messages are shared, not rebuilt).
    """
    _check_boxes(boxes)
    n = len(boxes)
    if status is not None and len(status) != n:
        raise MessageError(f"status has {len(status)} entries for {n} boxes")
    if texts is not None and len(texts) != n:
        raise MessageError(f"texts has {len(texts)} entries for {n} boxes")
    header = make_header(frame_id, stamp_ns, classes)

    def marker(**fields):
        return new_message("visualization_msgs/msg/Marker", classes, header=header, **fields)

    # Every box's markers are copies of one template per kind with the few fields that differ
    # set (typestore.from_template). The copies share the header (as every marker did before),
    # the identity pose, the scales and one colour per status; every list field is each
    # marker's own (a caller appending to one marker's points must not draw on all).
    lines = marker(ns=ns, type=LINE_LIST, action=ADD, pose=_pose(classes, (0.0, 0.0, 0.0), 0.0),
                   scale=_vector3(classes, (line_width, 0.0, 0.0)))
    labels = marker(ns=f"{ns}_text", type=TEXT_VIEW_FACING, action=ADD,
                    scale=_vector3(classes, (0.0, 0.0, text_height)))
    solids = marker(ns=f"{ns}_cubes", type=CUBE, action=ADD) if cubes else None
    colors: dict[tuple, object] = {}

    def color(rgba):
        if rgba not in colors:
            colors[rgba] = _color(classes, rgba)
        return colors[rgba]

    def stamp(template, **fields):
        return from_template(template, **{**{name: [] for name in _MARKER_LISTS}, **fields})

    markers = [marker(ns=ns, id=0, action=DELETEALL)]
    if edge_points is None:
        edge_points = box_edge_points(boxes, classes)
    elif len(edge_points) != n:
        raise MessageError(f"edge_points has {len(edge_points)} entries for {n} boxes")
    tops = boxes.center + np.c_[np.zeros((n, 2)), boxes.size[:, 2] / 2 + text_height]
    for i in range(n):
        rgba = STATUS_COLORS.get(None if status is None else str(status[i]), _OTHER_COLOR)
        markers.append(stamp(lines, id=i, color=color(rgba), points=edge_points[i]))
        markers.append(stamp(labels, id=i, pose=_pose(classes, tops[i], 0.0), color=color(rgba),
                             text=f"{boxes.label[i]} {boxes.score[i]:.2f}" if texts is None else str(texts[i])))
        if cubes:
            markers.append(stamp(solids, id=i, pose=_pose(classes, boxes.center[i], boxes.yaw[i]),
                                 scale=_vector3(classes, boxes.size[i]), color=color((*rgba[:3], 0.25)),
                                 text=str(boxes.label[i])))
    return new_message("visualization_msgs/msg/MarkerArray", classes, markers=markers)
