"""The rclpy node shared by ``completion_node`` and ``detection_filter_node``.

Thin by design (ros2/demos style): parameters in, pipeline frames out. Everything that
can be tested without ROS — pairing, the newest-wins hand-off, the pipeline, message
encoding, box transforms — lives outside this module.

Threading: subscription callbacks only pair messages and drop the pair into a
:class:`~pcc_ros.sync.LatestSlot`; one worker thread runs the pipeline on the newest pair
and publishes. A slow backend therefore drops frames (counted, reported on
``/diagnostics``) instead of building up latency.
"""

from __future__ import annotations

import importlib
import threading
import time

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import ParameterDescriptor, ParameterType
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from rclpy.time import Time
from sensor_msgs.msg import PointCloud2
from vision_msgs.msg import Detection3DArray
from visualization_msgs.msg import MarkerArray

from pcc_ros.errors import PccError
from pcc_ros.msg.stamps import stamp_to_ns
from pcc_ros.nodes.params import parameter_table
from pcc_ros.pipeline import Pipeline, PipelineConfig, build_outputs
from pcc_ros.sync import LatestSlot, StampPairer

_TYPES = {
    "bool": ParameterType.PARAMETER_BOOL,
    "integer": ParameterType.PARAMETER_INTEGER,
    "double": ParameterType.PARAMETER_DOUBLE,
    "string": ParameterType.PARAMETER_STRING,
    "string_array": ParameterType.PARAMETER_STRING_ARRAY,
}
RELIABLE = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE)


def rclpy_classes(name: str) -> type:
    """Message class of ``pkg/msg/Type`` from the ROS install (the rclpy-side resolver)."""
    package, _, type_name = name.split("/")
    return getattr(importlib.import_module(f"{package}.msg"), type_name)


class PipelineNode(Node):
    """Completion (``mode="completion"``) or detection filtering (``mode="filter"``)."""

    def __init__(self, node_name: str, mode: str, **node_options) -> None:
        """``node_options`` go to ``rclpy.node.Node`` (e.g. ``parameter_overrides`` in tests)."""
        super().__init__(node_name, **node_options)
        self.mode = mode
        for spec in parameter_table():
            self.declare_parameter(
                spec.name,
                list(spec.default) if isinstance(spec.default, tuple) else spec.default,
                ParameterDescriptor(description=spec.description, type=_TYPES[spec.type_name]),
            )
        values = {spec.name: self.get_parameter(spec.name).value for spec in parameter_table()}
        config = PipelineConfig.from_dict(values)
        self.pipeline = Pipeline(config)  # a missing/corrupt checkpoint fails here, at start-up, loudly
        self.pairer: StampPairer = StampPairer(
            slop_ns=int(values["sync_slop"] * 1e9), queue_size=int(values["queue_size"])
        )
        self.slot: LatestSlot = LatestSlot(self.pairer.stats)
        self.frames = 0
        self.failures = 0
        self.latency_ms: list[float] = []
        self._tf_buffer = self._make_tf_buffer()

        self.create_subscription(PointCloud2, "points", self._on_cloud, qos_profile_sensor_data)
        self.create_subscription(Detection3DArray, "detections", self._on_detections, RELIABLE)
        if mode == "completion":
            self.pub_cloud = self.create_publisher(PointCloud2, "completed", RELIABLE)
            self.pub_markers = self.create_publisher(MarkerArray, "completed_markers", RELIABLE)
        else:
            self.pub_kept = self.create_publisher(Detection3DArray, "detections_filtered", RELIABLE)
            self.pub_rejected = self.create_publisher(Detection3DArray, "detections_rejected", RELIABLE)
            self.pub_markers = self.create_publisher(MarkerArray, "filter_markers", RELIABLE)
        self.pub_diagnostics = self.create_publisher(DiagnosticArray, "/diagnostics", RELIABLE)
        self.create_timer(1.0, self._publish_diagnostics)
        self._running = True
        self._worker = threading.Thread(target=self._work, name=f"{node_name}_worker", daemon=True)
        self._worker.start()
        self.get_logger().info(
            f"{mode} node ready: backend={config.backend} classes={list(config.classes)} device={config.device}"
        )

    # ------------------------------------------------------------- callbacks

    def _on_cloud(self, msg: PointCloud2) -> None:
        pair = self.pairer.add_left(stamp_to_ns(msg.header.stamp), msg)
        if pair is not None:
            self.slot.put(pair)

    def _on_detections(self, msg: Detection3DArray) -> None:
        pair = self.pairer.add_right(stamp_to_ns(msg.header.stamp), msg)
        if pair is not None:
            self.slot.put(pair)

    def _work(self) -> None:
        while self._running:
            pair = self.slot.take(timeout=0.5)
            if pair is None:
                continue
            try:
                self._process(*pair)
            except PccError as exc:  # malformed input: log, skip, keep serving
                self.failures += 1
                self.get_logger().warning(f"skipped a frame: {exc}")
            except Exception as exc:  # a running node must not die on one frame
                self.failures += 1
                self.get_logger().error(f"frame failed: {type(exc).__name__}: {exc}")

    def _process(self, cloud: PointCloud2, detections: Detection3DArray) -> None:
        tic = time.perf_counter()
        if detections.header.frame_id and detections.header.frame_id != cloud.header.frame_id:
            detections = self._detections_in_frame(detections, cloud)
            if detections is None:
                return
        result, originals = self.pipeline.process_messages(cloud, detections)
        outputs = build_outputs(result, originals, rclpy_classes, detections_header=cloud.header)
        if self.mode == "completion":
            self.pub_cloud.publish(outputs["completed"])
        else:
            self.pub_kept.publish(outputs["detections_filtered"])
            self.pub_rejected.publish(outputs["detections_rejected"])
        self.pub_markers.publish(outputs["completed_markers"])
        self.frames += 1
        self.latency_ms.append((time.perf_counter() - tic) * 1e3)
        del self.latency_ms[:-200]
        if result.skipped:
            self.get_logger().debug(f"frame {result.stamp_ns}: skipped {result.skipped}")

    # ------------------------------------------------------------- tf2

    def _make_tf_buffer(self):
        try:
            from tf2_ros import Buffer, TransformListener
        except ImportError:
            return None
        buffer = Buffer()
        self._tf_listener = TransformListener(buffer, self)
        return buffer

    def _detections_in_frame(self, detections: Detection3DArray, cloud: PointCloud2):
        """Detections re-expressed in the cloud's frame through tf2, or None (logged)."""
        source, target = detections.header.frame_id, cloud.header.frame_id
        if self._tf_buffer is None:
            self.get_logger().warning(f"detections in '{source}', scan in '{target}' and tf2 is unavailable: skipped")
            return None
        try:
            tf = self._tf_buffer.lookup_transform(
                target, source, Time.from_msg(detections.header.stamp), timeout=Duration(seconds=0.05)
            )
        except Exception as exc:  # tf2 raises several unrelated exception types
            self.get_logger().warning(f"no transform '{source}' -> '{target}': {exc}; frame skipped")
            return None
        from pcc_ros.geometry.transforms import transform_boxes, transform_matrix
        from pcc_ros.msg.detections import boxes_from_detection_array, detection_array_from_boxes

        t, q = tf.transform.translation, tf.transform.rotation
        boxes = boxes_from_detection_array(detections, skip_invalid=True)
        moved = transform_boxes(boxes, transform_matrix((t.x, t.y, t.z), (q.x, q.y, q.z, q.w)))
        return detection_array_from_boxes(moved, target, stamp_to_ns(cloud.header.stamp), rclpy_classes)

    # ------------------------------------------------------------- diagnostics

    def _publish_diagnostics(self) -> None:
        stats = self.pairer.stats
        latency = np.array(self.latency_ms) if self.latency_ms else np.zeros(1)
        values = {
            "frames": self.frames,
            "failed_frames": self.failures,
            "paired": stats.paired,
            "dropped_clouds": stats.dropped_clouds,
            "dropped_detections": stats.dropped_detections,
            "dropped_pairs_newest_wins": stats.dropped_pairs,
            "latency_p50_ms": f"{np.percentile(latency, 50):.1f}",
            "latency_p95_ms": f"{np.percentile(latency, 95):.1f}",
        }
        status = DiagnosticStatus(
            level=DiagnosticStatus.OK if not self.failures else DiagnosticStatus.WARN,
            name=f"pcc_ros: {self.get_name()}",
            message=f"{self.frames} frames",
            hardware_id="pcc_ros",
            values=[KeyValue(key=k, value=str(v)) for k, v in values.items()],
        )
        self.pub_diagnostics.publish(DiagnosticArray(header=self._stamp_header(), status=[status]))

    def _stamp_header(self):
        from std_msgs.msg import Header

        return Header(stamp=self.get_clock().now().to_msg())

    def destroy_node(self) -> None:
        self._running = False
        self.slot.close()
        self._worker.join(timeout=2.0)
        super().destroy_node()


def run(node_name: str, mode: str, args: list[str] | None = None) -> int:
    """``main()`` of both nodes: init, spin, clean shutdown on Ctrl-C / external shutdown."""
    from rclpy.executors import ExternalShutdownException

    rclpy.init(args=args)
    node = None
    try:
        node = PipelineNode(node_name, mode)
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except PccError as exc:
        (node.get_logger() if node else rclpy.logging.get_logger(node_name)).fatal(str(exc))
        return 1
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0
