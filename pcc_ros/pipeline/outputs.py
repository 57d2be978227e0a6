"""The messages a node publishes for one frame, built from the pipeline's :class:`FrameResult`.

Kept apart from :mod:`pcc_ros.pipeline.core` (which computes a frame) because this is the
wire side: the completed cloud's point layout and colours, the RViz marker texts and the
re-published detection arrays. A node builds only the outputs it publishes (``names``).
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Sequence
from typing import Any

import numpy as np

from pcc_ros.msg.detections import box_edge_points, detection_array_from_boxes, marker_array_from_boxes
from pcc_ros.msg.pointcloud2 import create_cloud
from pcc_ros.msg.stamps import make_header
from pcc_ros.msg.typestore import new_message
from pcc_ros.pipeline.core import FrameResult
from pcc_ros.pipeline.filter import annotate_detections, mark_unjudged

#: Layout of the published completed cloud (28 bytes a point): ``instance`` = index of the
#: detection in its array (-1 for raw scan points), ``source`` = :data:`~pcc_ros.pipeline.core.SOURCE_OBSERVED` (a
#: LiDAR return) or :data:`~pcc_ros.pipeline.core.SOURCE_COMPLETED` (made by the backend), ``rgb`` = a per-instance
#: colour packed as RViz's float ``rgb`` (0x00RRGGBB; raw scan points grey), ``score`` = the
#: detection's score as the detector gave it (NaN for raw scan points).
COMPLETED_CLOUD_DTYPE = np.dtype(
    {
        "names": ["x", "y", "z", "instance", "rgb", "score", "source"],
        "formats": ["<f4", "<f4", "<f4", "<i4", "<f4", "<f4", "u1"],
        "offsets": [0, 4, 8, 12, 16, 20, 24],
        "itemsize": 28,
    }
)
#: Instance colours (tab10), cycled by detection index; raw scan points are grey.
INSTANCE_PALETTE = np.array(
    [
        [31, 119, 180], [255, 127, 14], [44, 160, 44], [214, 39, 40], [148, 103, 189],
        [140, 86, 75], [227, 119, 194], [188, 189, 34], [23, 190, 207], [127, 127, 127],
    ],
    dtype=np.uint32,
)
RAW_POINT_RGB = (160, 160, 160)
#: PCL's packed ``rgb`` (0x00RRGGBB) of each palette colour, then the raw points' grey last.
_PACKED_RGB = np.array(
    [(r << 16) | (g << 8) | b for r, g, b in (*INSTANCE_PALETTE.tolist(), RAW_POINT_RGB)], dtype=np.uint32
)

#: The outputs :func:`build_outputs` makes (default topic names), in the order it makes them.
OUTPUT_NAMES = ("completed", "completed_markers", "filter_markers", "detections_filtered", "detections_rejected")
#: The outputs that republish the input detection messages (:meth:`Pipeline.process_messages`'s originals).
DETECTION_OUTPUTS = ("detections_filtered", "detections_rejected")
#: The RViz outputs (boxes and texts), which a node builds only while something subscribes to them.
MARKER_OUTPUTS = ("completed_markers", "filter_markers")


def build_outputs(
    result: FrameResult,
    original_detections: Sequence | None = None,
    classes: Callable[[str], type] | None = None,
    detections_header=None,
    names: Collection[str] = OUTPUT_NAMES,
) -> dict[str, Any]:
    """The messages a node publishes for one frame, keyed by default topic name: those of
    ``names`` (default every one; a node asks for the ones it publishes, nothing else is built).

    ``completed`` (PointCloud2 of :data:`COMPLETED_CLOUD_DTYPE`: x, y, z, instance, rgb,
    score, source), ``completed_markers`` (MarkerArray: boxes coloured by filter decision,
    text "<label> <score>"), ``filter_markers`` (the same boxes, text "<label> p=<mapped
    score> m=<mismatch> <decision>"), ``detections_filtered`` / ``detections_rejected``
    (Detection3DArray: the original detection messages when given, so every hypothesis and
    id survives untouched, else re-encoded from the boxes).
    """
    unknown = sorted(set(names) - set(OUTPUT_NAMES))
    if unknown:
        raise ValueError(f"unknown output(s) {unknown}; known: {list(OUTPUT_NAMES)}")
    outputs: dict[str, Any] = {}
    if "completed" in names:
        outputs["completed"] = create_cloud(completed_cloud_array(result), None, result.frame_id, result.stamp_ns,
                                            classes)
    markers = [(name, ns) for name, ns in (("completed_markers", "pcc"), ("filter_markers", "pcc_filter"))
               if name in names]
    edges = box_edge_points(result.detections, classes) if markers else None  # both marker arrays draw the same boxes
    for name, ns in markers:
        texts = filter_texts(result) if name == "filter_markers" else None
        outputs[name] = marker_array_from_boxes(
            result.detections, result.frame_id, result.stamp_ns, status=result.status, ns=ns, classes=classes,
            texts=texts, edge_points=edges,
        )
    keep = result.keep
    for topic, mask in (("detections_filtered", keep), ("detections_rejected", ~keep)):
        if topic not in names:
            continue
        if original_detections is not None:
            header = detections_header or make_header(result.frame_id, result.stamp_ns, classes)
            chosen = [d for d, m in zip(original_detections, mask) if m]
            annotated = annotate_detections(chosen, result, np.flatnonzero(mask), classes)
            if topic == "detections_filtered" and result.unjudged_originals:  # boxes failing the checks
                annotated += mark_unjudged(result.unjudged_originals, classes)
            outputs[topic] = new_message(
                "vision_msgs/msg/Detection3DArray", classes, header=header, detections=annotated,
            )
        else:
            array = detection_array_from_boxes(result.detections[mask], result.frame_id, result.stamp_ns, classes)
            array.detections = annotate_detections(list(array.detections), result, np.flatnonzero(mask), classes)
            outputs[topic] = array
    return outputs


def completed_cloud_array(result: FrameResult) -> np.ndarray:
    """The structured points of the ``completed`` cloud (:data:`COMPLETED_CLOUD_DTYPE`)."""
    instance = result.completed_instance
    cloud = np.zeros(len(result.completed_points), dtype=COMPLETED_CLOUD_DTYPE)
    cloud["x"], cloud["y"], cloud["z"] = result.completed_points.T
    cloud["instance"] = instance
    cloud["source"] = result.completed_source
    # Per-point lookups through one table each, the raw points (instance -1) reading the last
    # entry: a gather per field instead of masked gathers and scatters.
    palette = len(INSTANCE_PALETTE)
    colour = np.where(instance >= 0, instance % palette, palette)
    cloud["rgb"] = _PACKED_RGB.take(colour).view(np.float32)
    scores = np.append(result.detections.score.astype(np.float32), np.float32(np.nan))
    cloud["score"] = scores.take(np.where(instance >= 0, instance, len(scores) - 1))
    return cloud


def filter_texts(result: FrameResult) -> list[str]:
    """One RViz label per detection: class, mapped score, then the evidence rule's probability
    that the detection is false (``p_false=``) or the TraPCC mismatch score (``m=``), and the decision."""
    probability = result.probability if result.probability is not None else result.detections.score
    false = result.filter_score if result.filter_score is not None else np.full(len(probability), np.nan)
    texts = []
    for label, p, f, m, status in zip(result.detections.label, probability, false, result.mismatch, result.status):
        if np.isfinite(f):
            texts.append(f"{label} p={p:.2f} p_false={f:.2f} {status}")
        else:
            mismatch = f"m={m:.2f}" if np.isfinite(m) else "m=-"
            texts.append(f"{label} p={p:.2f} {mismatch} {status}")
    return texts
