"""The node logic shared by every runtime: pairing, newest-wins worker, pipeline, publishing, diagnostics.

:class:`NodeCore` knows nothing of rclpy or DDS; it talks to a
:class:`~pcc_ros.runtime.base.Runtime` (rclpy in :mod:`pcc_ros.nodes.ros_node`, Cyclone DDS
in :mod:`pcc_ros.runtime.dds`, in-process in :mod:`pcc_ros.runtime.local`), so all three
run the very same code.

Threading: subscription callbacks only pair messages and drop the pair into a
:class:`~pcc_ros.sync.LatestSlot`; one worker thread runs the pipeline on the newest pair
and publishes. A slow backend therefore drops frames (counted, reported on
``/diagnostics``) instead of building up latency. ``threaded=False`` processes each pair
inside the callback instead (offline use: nothing may be dropped).
"""

from __future__ import annotations

import threading
import time
from typing import Any

import numpy as np

from pcc_ros.errors import ConfigError, PccError
from pcc_ros.msg.stamps import make_header, stamp_to_ns
from pcc_ros.msg.typestore import new_message
from pcc_ros.nodes.params import NODE_DEFAULTS, parameter_table
from pcc_ros.pipeline import Pipeline, PipelineConfig, build_outputs
from pcc_ros.runtime.base import RELIABLE, SENSOR_DATA, Runtime
from pcc_ros.sync import LatestSlot, StampPairer

MODES = ("completion", "filter")

#: Default topics (relative names, remappable) -> message type, per mode.
INPUTS = {"points": "sensor_msgs/msg/PointCloud2", "detections": "vision_msgs/msg/Detection3DArray"}
OUTPUTS = {
    "completion": {
        "completed": "sensor_msgs/msg/PointCloud2",
        "completed_markers": "visualization_msgs/msg/MarkerArray",
    },
    "filter": {
        "detections_filtered": "vision_msgs/msg/Detection3DArray",
        "detections_rejected": "vision_msgs/msg/Detection3DArray",
        "filter_markers": "visualization_msgs/msg/MarkerArray",
    },
}
DIAGNOSTICS_TOPIC = "/diagnostics"
#: build_outputs() key of each output topic.
_OUTPUT_KEY = {"filter_markers": "completed_markers"}


def node_parameters(values: dict[str, Any] | None = None) -> dict[str, Any]:
    """Every node parameter: the defaults of the parameter table overridden by ``values``.

    Unknown names raise :class:`ConfigError` (a YAML typo must not be silently ignored).
    """
    table = {spec.name: spec.default for spec in parameter_table()}
    values = dict(values or {})
    values.pop("use_sim_time", None)
    unknown = set(values) - set(table)
    if unknown:
        raise ConfigError(f"unknown node parameter(s): {sorted(unknown)}")
    merged = {**table, **values}
    merged["classes"] = list(merged["classes"])
    return merged


class NodeCore:
    """Completion (``mode="completion"``) or detection filtering (``mode="filter"``) on any runtime.

    Args:
        runtime: the node's middleware handle.
        node_name: used in logs and the diagnostics status name.
        mode: ``"completion"`` or ``"filter"``.
        parameters: flat node parameters (see :func:`node_parameters`).
        pipeline: a ready pipeline (tests, benchmarks); by default built from ``parameters``.
        threaded: process on a worker thread, newest pair wins (a live node); ``False``
            processes each pair in the subscription callback (offline).
        remap: default topic name -> actual name.
    """

    def __init__(
        self,
        runtime: Runtime,
        node_name: str,
        mode: str,
        parameters: dict[str, Any] | None = None,
        pipeline: Pipeline | None = None,
        threaded: bool = True,
        remap: dict[str, str] | None = None,
    ) -> None:
        if mode not in MODES:
            raise ConfigError(f"node mode must be one of {MODES}, not {mode!r}")
        self.runtime, self.node_name, self.mode = runtime, node_name, mode
        self.log = runtime.get_logger()
        values = node_parameters(parameters)
        self.parameters = values
        config = PipelineConfig.from_dict({k: v for k, v in values.items() if k not in NODE_DEFAULTS})
        self.pipeline = pipeline or Pipeline(config)  # a missing/corrupt checkpoint fails here, loudly
        self.pairer: StampPairer = StampPairer(
            slop_ns=int(float(values["sync_slop"]) * 1e9), queue_size=int(values["queue_size"])
        )
        self.slot: LatestSlot = LatestSlot(self.pairer.stats)
        self.frames = 0
        self.failures = 0
        self.latency_ms: list[float] = []
        remap = remap or {}
        self.topics = {name: remap.get(name, name) for name in [*INPUTS, *OUTPUTS[mode]]}

        self.publishers = {
            name: runtime.create_publisher(self.topics[name], msgtype, RELIABLE)
            for name, msgtype in OUTPUTS[mode].items()
        }
        self.pub_diagnostics = runtime.create_publisher(
            DIAGNOSTICS_TOPIC, "diagnostic_msgs/msg/DiagnosticArray", RELIABLE
        )
        runtime.create_subscription(self.topics["points"], INPUTS["points"], self.on_cloud, SENSOR_DATA)
        runtime.create_subscription(self.topics["detections"], INPUTS["detections"], self.on_detections, RELIABLE)
        runtime.create_timer(1.0, self.publish_diagnostics)

        self.threaded = threaded
        self._running = threaded
        self._worker = None
        if threaded:
            self._worker = threading.Thread(target=self._work, name=f"{node_name}_worker", daemon=True)
            self._worker.start()
        self.log.info(
            f"{mode} node ready: backend={config.backend} classes={list(config.classes)} device={config.device}"
        )

    # ------------------------------------------------------------- callbacks

    def on_cloud(self, msg) -> None:
        self._pair(self.pairer.add_left, msg)

    def on_detections(self, msg) -> None:
        self._pair(self.pairer.add_right, msg)

    def _pair(self, add, msg) -> None:
        try:
            stamp = stamp_to_ns(msg.header.stamp)
        except (PccError, AttributeError) as exc:
            self.failures += 1
            self.log.warning(f"message without a usable header skipped: {exc}")
            return
        pair = add(stamp, msg)
        if pair is None:
            return
        if self.threaded:
            self.slot.put(pair)
        else:
            self._process_logged(*pair)

    def _work(self) -> None:
        while self._running:
            pair = self.slot.take(timeout=0.5)
            if pair is not None:
                self._process_logged(*pair)

    def _process_logged(self, cloud, detections) -> None:
        try:
            self.process(cloud, detections)
        except PccError as exc:  # malformed input: log, skip, keep serving
            self.failures += 1
            self.log.warning(f"skipped a frame: {exc}")
        except Exception as exc:  # a running node must not die on one frame
            self.failures += 1
            self.log.error(f"frame failed: {type(exc).__name__}: {exc}")

    # ------------------------------------------------------------- work

    def process(self, cloud, detections) -> dict[str, Any] | None:
        """Run one pair through the pipeline and publish; returns the published messages (None: skipped)."""
        tic = time.perf_counter()
        if detections.header.frame_id and detections.header.frame_id != cloud.header.frame_id:
            detections = self._detections_in_frame(detections, cloud)
            if detections is None:
                return None
        result, originals = self.pipeline.process_messages(cloud, detections)
        outputs = build_outputs(result, originals, self.runtime.classes, detections_header=cloud.header)
        published = {name: outputs[_OUTPUT_KEY.get(name, name)] for name in self.publishers}
        for name, msg in published.items():
            self.publishers[name].publish(msg)
        self.frames += 1
        self.latency_ms.append((time.perf_counter() - tic) * 1e3)
        del self.latency_ms[:-200]
        if result.skipped:
            self.log.debug(f"frame {result.stamp_ns}: skipped {result.skipped}")
        return published

    def _detections_in_frame(self, detections, cloud):
        """Detections re-expressed in the cloud's frame through the runtime's transforms, or None (logged)."""
        from pcc_ros.geometry.transforms import transform_boxes
        from pcc_ros.msg.detections import boxes_from_detection_array, detection_array_from_boxes

        source, target = detections.header.frame_id, cloud.header.frame_id
        tf = self.runtime.lookup_transform(target, source, stamp_to_ns(detections.header.stamp))
        if tf is None:
            self.failures += 1
            self.log.warning(f"no transform '{source}' -> '{target}'; frame skipped")
            return None
        boxes = boxes_from_detection_array(detections, skip_invalid=True)
        moved = transform_boxes(boxes, tf.matrix())
        return detection_array_from_boxes(moved, target, stamp_to_ns(cloud.header.stamp), self.runtime.classes)

    # ------------------------------------------------------------- diagnostics

    def diagnostics_values(self) -> dict[str, str]:
        """The key/values of the node's diagnostics status (counters and latency percentiles)."""
        stats = self.pairer.stats
        latency = np.array(self.latency_ms) if self.latency_ms else np.zeros(1)
        values = {
            "frames": self.frames,
            "failed_frames": self.failures,
            "undecodable_samples": getattr(self.runtime, "undecodable", 0),
            "paired": stats.paired,
            "dropped_clouds": stats.dropped_clouds,
            "dropped_detections": stats.dropped_detections,
            "dropped_pairs_newest_wins": stats.dropped_pairs,
            "latency_p50_ms": f"{np.percentile(latency, 50):.1f}",
            "latency_p95_ms": f"{np.percentile(latency, 95):.1f}",
        }
        return {k: str(v) for k, v in values.items()}

    def diagnostics_message(self):
        """A ``diagnostic_msgs/DiagnosticArray`` of the runtime's class flavour (level WARN after failures)."""
        classes = self.runtime.classes
        failed = self.failures or getattr(self.runtime, "undecodable", 0)
        status = new_message(
            "diagnostic_msgs/msg/DiagnosticStatus",
            classes,
            level=bytes([1 if failed else 0]) if _byte_is_bytes(classes) else (1 if failed else 0),
            name=f"pcc_ros: {self.node_name}",
            message=f"{self.frames} frames",
            hardware_id="pcc_ros",
            values=[
                new_message("diagnostic_msgs/msg/KeyValue", classes, key=k, value=v)
                for k, v in self.diagnostics_values().items()
            ],
        )
        header = make_header("", self.runtime.now_ns(), classes)
        return new_message("diagnostic_msgs/msg/DiagnosticArray", classes, header=header, status=[status])

    def publish_diagnostics(self) -> None:
        try:
            self.pub_diagnostics.publish(self.diagnostics_message())
        except Exception as exc:  # diagnostics must never take the node down
            self.log.error(f"diagnostics failed: {type(exc).__name__}: {exc}")

    def shutdown(self) -> None:
        """Stop the worker (pending pair dropped); the runtime closes its own entities."""
        self._running = False
        self.slot.close()
        if self._worker is not None:
            self._worker.join(timeout=2.0)


def _byte_is_bytes(classes) -> bool:
    """rclpy's generated classes type ``byte`` fields as ``bytes``; rosbags uses ints."""
    from pcc_ros.msg.typestore import is_rosbags_class

    return not is_rosbags_class(classes("diagnostic_msgs/msg/DiagnosticStatus"))
