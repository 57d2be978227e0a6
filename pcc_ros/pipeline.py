"""The per-frame pipeline: scan + detections in, completions and filter decisions out.

One class serves every runtime — the rclpy nodes, the DDS runtime, ``pcc replay`` and
the demo — and knows nothing of rclpy: the nodes only feed it frames and publish what
it returns, so offline results are exactly what a running node would publish.

Stages (each timed): decode -> crop (points in the configured classes' boxes, ground
returns removed) -> canonical frame -> complete (one batched backend call) -> back to
the scan frame -> shape-mismatch score -> keep / reject -> encode.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

from pcc_ros.boxes import Boxes, class_mask
from pcc_ros.errors import ConfigError
from pcc_ros.filter import FilterConfig, mismatch_scores, reject_mask
from pcc_ros.geometry.boxes import crop_canonical
from pcc_ros.geometry.canonical import from_canonical

log = logging.getLogger(__name__)

#: Layout of the published completed cloud.
COMPLETED_CLOUD_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("instance", "<i4")])
#: ``instance`` value of raw scan points in the completed cloud (``include_input_points``).
RAW_POINT_INSTANCE = -1


@dataclass(frozen=True)
class PipelineConfig:
    """Every knob of the pipeline; the nodes declare one ROS parameter per field."""

    backend: str = "pointpncnet"
    checkpoint: str = ""
    device: str = "auto"
    classes: tuple[str, ...] = ("Car", "Van")
    min_points: int = 20
    max_instances: int = 32
    box_margin: float = 0.1
    ground_margin: float = 0.05
    batch_size: int = 32
    include_input_points: bool = False
    filter: FilterConfig = field(default_factory=FilterConfig)

    def __post_init__(self) -> None:
        if self.min_points < 1 or self.max_instances < 1 or self.batch_size < 1:
            raise ConfigError("min_points, max_instances and batch_size must be >= 1")
        if self.box_margin < 0 or self.ground_margin < 0:
            raise ConfigError("box_margin and ground_margin must be >= 0")
        object.__setattr__(self, "classes", tuple(str(c) for c in self.classes))

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> PipelineConfig:
        """From flat parameters (a YAML ``ros__parameters`` block, ROS parameters, CLI).

        Unknown keys that are not runtime options of a node raise :class:`ConfigError`, so
        a typo in a YAML file is reported instead of silently ignored.
        """
        own = {f.name for f in fields(cls)} - {"filter"}
        filter_keys = {f.name for f in fields(FilterConfig)}
        unknown = set(values) - own - filter_keys - NODE_ONLY_PARAMETERS
        if unknown:
            raise ConfigError(f"unknown pipeline parameter(s): {sorted(unknown)}")
        main = {k: v for k, v in values.items() if k in own}
        if "classes" in main:
            main["classes"] = tuple(main["classes"])
        filt = FilterConfig(**{k: v for k, v in values.items() if k in filter_keys})
        return cls(**main, filter=filt)

    @classmethod
    def from_yaml(cls, path: str | Path, node_name: str | None = None) -> PipelineConfig:
        """Read a ``config/*.yaml`` node parameter file (the first node when no name is given)."""
        return cls.from_dict(read_parameters(path, node_name))

    def as_parameters(self) -> dict[str, Any]:
        """Flat parameter dict (the inverse of :meth:`from_dict`)."""
        out = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "filter"}
        out["classes"] = list(self.classes)
        out.update({f.name: getattr(self.filter, f.name) for f in fields(FilterConfig)})
        return out


#: Parameters the node shells read themselves (pairing, queues), with their defaults; the
#: pipeline ignores them (and ROS's own ``use_sim_time``).
NODE_DEFAULTS: dict[str, Any] = {"sync_slop": 0.05, "queue_size": 5}
NODE_ONLY_PARAMETERS = frozenset({*NODE_DEFAULTS, "use_sim_time"})


def read_parameters(path: str | Path, node_name: str | None = None) -> dict[str, Any]:
    """The ``ros__parameters`` block of one node in a ROS 2 YAML parameter file."""
    import yaml

    path = Path(path)
    try:
        document = yaml.safe_load(path.read_text()) or {}
    except (OSError, yaml.YAMLError) as exc:
        raise ConfigError(f"{path}: cannot read parameter file ({exc})") from exc
    if node_name is None:
        if not document:
            raise ConfigError(f"{path}: no node in parameter file")
        node_name = next(iter(document))
    block = document.get(node_name) or document.get(f"/{node_name}") or document.get("/**")
    if not isinstance(block, dict) or "ros__parameters" not in block:
        raise ConfigError(f"{path}: no '{node_name}: ros__parameters:' block")
    return dict(block["ros__parameters"])


@dataclass
class FrameResult:
    """Everything one frame produces, in the scan's frame ``frame_id``.

    Per-detection arrays have one row per input detection (after invalid boxes were
    dropped, see ``skipped``): ``status`` is ``"kept"``, ``"rejected"`` or ``"skipped"``
    (another class, too few points, over the per-frame cap — skipped detections pass the
    filter untouched), ``mismatch`` is NaN where no shape was judged.
    """

    stamp_ns: int
    frame_id: str
    detections: Boxes
    completed_points: np.ndarray  # (M, 3) float32, scan frame
    completed_instance: np.ndarray  # (M,) int32: detection index, RAW_POINT_INSTANCE for raw points
    crops: list[np.ndarray]  # canonical crops of the completed detections
    completions: list[np.ndarray]  # canonical completions, same order
    completed_index: np.ndarray  # detection index of each completion
    num_points: np.ndarray  # (N,) points inside each detection box
    mismatch: np.ndarray  # (N,)
    status: np.ndarray  # (N,) object
    timings_ms: dict[str, float] = field(default_factory=dict)
    skipped: dict[str, int] = field(default_factory=dict)

    @property
    def keep(self) -> np.ndarray:
        return self.status != "rejected"

    @property
    def kept(self) -> Boxes:
        return self.detections[self.keep]

    @property
    def rejected(self) -> Boxes:
        return self.detections[~self.keep]


class Pipeline:
    """Completion and shape-mismatch filtering of one frame at a time.

    Args:
        config: the parameters.
        completer: a ready backend; by default loaded from ``config.backend`` /
            ``config.checkpoint`` (the shipped default checkpoint when empty).
    """

    def __init__(self, config: PipelineConfig, completer=None) -> None:
        self.config = config
        if completer is None:
            from pcc_ros.models.base import load_completer

            completer = load_completer(
                config.backend, config.checkpoint or None, device=config.device, **self._runtime_options(config)
            )
        self.completer = completer

    @staticmethod
    def _runtime_options(config: PipelineConfig) -> dict[str, Any]:
        from pcc_ros.models.base import get_backend

        return {"batch_size": config.batch_size} if get_backend(config.backend).learned else {}

    # ------------------------------------------------------------------ core

    def process(self, points: np.ndarray, detections: Boxes, stamp_ns: int = 0, frame_id: str = "") -> FrameResult:
        """Run one frame. ``points``: ``(N, >=3)`` finite scan points; ``detections``: valid boxes."""
        cfg = self.config
        timings: dict[str, float] = {}
        n = len(detections)
        status = np.full(n, "skipped", dtype=object)
        mismatch = np.full(n, np.nan)
        num_points = np.zeros(n, dtype=np.int64)
        skipped: dict[str, int] = {}

        tic = time.perf_counter()
        wanted = class_mask(detections.label, cfg.classes)  # other classes pass the filter untouched
        _count(skipped, "other class", int((~wanted).sum()))
        candidates = np.flatnonzero(wanted)
        if len(candidates) > cfg.max_instances:
            order = np.argsort(-detections.score[candidates], kind="stable")
            dropped = candidates[order[cfg.max_instances :]]
            _count(skipped, "over max_instances", len(dropped))
            candidates = np.sort(candidates[order[: cfg.max_instances]])
        _, canonical = crop_canonical(points, detections[candidates], cfg.box_margin, cfg.ground_margin)
        counts = np.array([len(c) for c in canonical], dtype=np.int64)
        num_points[candidates] = counts
        timings["crop_ms"] = _ms(tic)

        enough = counts >= cfg.min_points
        empty = counts == 0
        _count(skipped, "too few points", int((~enough & ~empty).sum()))
        # A box with no return at all holds no vehicle evidence: maximal mismatch, so the
        # score gate alone decides (a confident detection of an occluded car survives).
        mismatch[candidates[empty]] = 1.0

        tic = time.perf_counter()
        selected = candidates[enough]
        crops = [canonical[i] for i in np.flatnonzero(enough)]
        context = None
        if getattr(self.completer, "uses_context", False) and crops:
            from pcc_ros.models.base import SceneContext

            context = SceneContext.from_frame(detections[selected], crops)
        completions = self.completer.complete(crops, context) if crops else []
        timings["complete_ms"] = _ms(tic)

        tic = time.perf_counter()
        if crops:
            mismatch[selected] = mismatch_scores(crops, completions, cfg.filter)
        judged = np.isfinite(mismatch)
        rejected = reject_mask(mismatch, detections.score, cfg.filter)
        status[judged] = np.where(rejected[judged], "rejected", "kept")
        timings["filter_ms"] = _ms(tic)

        tic = time.perf_counter()
        sensor = [
            from_canonical(c, detections.center[i], detections.yaw[i], detections.size[i, 0])
            for c, i in zip(completions, selected)
        ]
        parts = [s.astype(np.float32) for s in sensor]
        instance = [np.full(len(s), i, dtype=np.int32) for s, i in zip(sensor, selected)]
        if cfg.include_input_points:
            parts.insert(0, np.ascontiguousarray(points[:, :3], dtype=np.float32))
            instance.insert(0, np.full(len(points), RAW_POINT_INSTANCE, dtype=np.int32))
        completed = np.concatenate(parts) if parts else np.zeros((0, 3), np.float32)
        instance_ids = np.concatenate(instance) if instance else np.zeros(0, np.int32)
        timings["uncanonical_ms"] = _ms(tic)

        return FrameResult(
            stamp_ns=int(stamp_ns),
            frame_id=frame_id,
            detections=detections,
            completed_points=completed,
            completed_instance=instance_ids,
            crops=crops,
            completions=completions,
            completed_index=selected,
            num_points=num_points,
            mismatch=mismatch,
            status=status,
            timings_ms=timings,
            skipped=skipped,
        )

    # ------------------------------------------------------------------ messages

    def process_messages(self, cloud_msg, detections_msg) -> tuple[FrameResult, Any]:
        """Decode a PointCloud2 and a Detection3DArray (any message classes) and run the frame.

        Invalid detections (NaN pose, non-positive size) are dropped with a warning and
        counted in ``skipped``; a malformed cloud or array, or detections in another frame
        than the scan, raise :class:`pcc_ros.errors.MessageError` for the caller to log and skip.
        Returns the result and the valid subset of ``detections_msg.detections``, in the
        order of ``result.detections`` (so the outputs republish the original messages).
        """
        from pcc_ros.errors import MessageError
        from pcc_ros.msg.detections import decode_detection_array
        from pcc_ros.msg.pointcloud2 import read_xyz
        from pcc_ros.msg.stamps import stamp_to_ns

        cloud_frame, boxes_frame = str(cloud_msg.header.frame_id), str(detections_msg.header.frame_id)
        if boxes_frame and boxes_frame != cloud_frame:
            raise MessageError(
                f"detections are in frame '{boxes_frame}' but the scan is in '{cloud_frame}': "
                "transform them first (the nodes do it with tf2)"
            )
        tic = time.perf_counter()
        points = read_xyz(cloud_msg)
        boxes, valid = decode_detection_array(detections_msg, skip_invalid=True)
        originals = [d for d, ok in zip(detections_msg.detections, valid) if ok]
        decode_ms = _ms(tic)
        result = self.process(
            points, boxes, stamp_to_ns(cloud_msg.header.stamp), str(cloud_msg.header.frame_id)
        )
        result.timings_ms = {"decode_ms": decode_ms, **result.timings_ms}
        _count(result.skipped, "invalid detection", int((~valid).sum()))
        return result, originals


def build_outputs(
    result: FrameResult,
    original_detections: Sequence | None = None,
    classes: Callable[[str], type] | None = None,
    detections_header=None,
) -> dict[str, Any]:
    """The messages a node publishes for one frame, keyed by default topic name.

    ``completed`` (PointCloud2 x, y, z, instance), ``completed_markers`` (MarkerArray:
    boxes coloured by filter decision), ``detections_filtered`` / ``detections_rejected``
    (Detection3DArray: the original detection messages when given, so every hypothesis
    and id survives untouched, else re-encoded from the boxes).
    """
    from pcc_ros.msg.detections import detection_array_from_boxes, marker_array_from_boxes
    from pcc_ros.msg.pointcloud2 import create_cloud
    from pcc_ros.msg.stamps import make_header
    from pcc_ros.msg.typestore import new_message

    cloud = np.zeros(len(result.completed_points), dtype=COMPLETED_CLOUD_DTYPE)
    cloud["x"], cloud["y"], cloud["z"] = result.completed_points.T
    cloud["instance"] = result.completed_instance
    outputs = {
        "completed": create_cloud(cloud, None, result.frame_id, result.stamp_ns, classes),
        "completed_markers": marker_array_from_boxes(
            result.detections, result.frame_id, result.stamp_ns, status=result.status, ns="pcc", classes=classes
        ),
    }
    keep = result.keep
    for topic, mask in (("detections_filtered", keep), ("detections_rejected", ~keep)):
        if original_detections is not None:
            header = detections_header or make_header(result.frame_id, result.stamp_ns, classes)
            chosen = [d for d, m in zip(original_detections, mask) if m]
            outputs[topic] = new_message(
                "vision_msgs/msg/Detection3DArray", classes, header=header, detections=chosen
            )
        else:
            outputs[topic] = detection_array_from_boxes(
                result.detections[mask], result.frame_id, result.stamp_ns, classes
            )
    return outputs


def _count(counter: dict[str, int], reason: str, n: int) -> None:
    if n:
        counter[reason] = counter.get(reason, 0) + n


def _ms(tic: float) -> float:
    return (time.perf_counter() - tic) * 1e3

