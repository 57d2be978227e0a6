"""The node logic shared by every runtime: pairing, newest-wins worker, pipeline, publishing, diagnostics.

:class:`NodeCore` knows nothing of rclpy; it talks to a
:class:`~pcc_ros.runtime.base.Runtime` (rclpy in :mod:`pcc_ros.nodes.ros_node`, in-process
in :mod:`pcc_ros.runtime.local`), so live nodes, tests and replay run the very same code.

Threading: subscription callbacks only pair messages and drop the pair into a
:class:`~pcc_ros.runtime.pairing.LatestSlot`; one worker thread runs the pipeline on the newest pair
and publishes. A slow backend therefore drops frames (counted, reported on
``/diagnostics``) instead of building up latency. ``threaded=False`` processes each pair
inside the callback instead (offline use: nothing may be dropped).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from pcc_ros.errors import ConfigError, PccError
from pcc_ros.geometry.transforms import transform_boxes
from pcc_ros.lograte import worth_logging
from pcc_ros.msg.detections import transform_detections
from pcc_ros.msg.stamps import make_header, stamp_to_ns
from pcc_ros.msg.transforms import frame_name, same_frame
from pcc_ros.msg.typestore import is_rosbags_class, new_message
from pcc_ros.pipeline.config import (
    BACKEND_PARAMETERS,
    check_value,
    integer_id,
    node_parameters,
    parameter_specs,
    pipeline_config,
    unknown_parameters,
)
from pcc_ros.pipeline.core import DETECTION_OUTPUTS, MARKER_OUTPUTS, FrameResult, Pipeline, build_outputs
from pcc_ros.pipeline.filter import DECISIONS, decision_counts
from pcc_ros.runtime.base import RELIABLE, QoS, Runtime
from pcc_ros.runtime.heap import freeze_long_lived
from pcc_ros.runtime.pairing import LatestSlot, StampPairer
from pcc_ros.types import class_mask

MODES = ("completion", "filter")
#: At most this many distinct class ids outside ``classes`` are reported (hostile labels stay bounded).
_REPORTED_CLASSES = 64

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

#: The logger of the node whose work runs here now (:func:`working_for`; a context variable, so per
#: thread): a line the package's modules log meanwhile (the pipeline, the message decoders, a backend
#: loading) is that node's line: its record is tagged with the node (``pcc_node``), and the rclpy host says it on
#: that node's ROS logger only (:class:`pcc_ros.nodes.ros_node.RclpyLogHandler`).
node_at_work: ContextVar[Any] = ContextVar("pcc_ros_node_at_work", default=None)


@contextmanager
def working_for(logger: Any) -> Iterator[None]:
    """The package's log records of this block are the lines of the node whose logger is ``logger``."""
    token = node_at_work.set(logger)
    try:
        yield
    finally:
        node_at_work.reset(token)


def _tagged_with_the_node(factory):
    """A log record factory: a record of a ``pcc_ros.*`` module logger made while a node works
    carries the node's logger name as ``record.pcc_node`` (its ``name`` stays the module's, so
    logging filters by module keep working); ``pcc``'s console shows it in the name's place
    (``pcc replay``: ``WARNING pcc_ros.detection_filter_node: ...``, as the node's own lines)."""

    def make(name, *args, **kwargs):
        record = factory(name, *args, **kwargs)
        node = node_at_work.get()
        if node is not None and isinstance(name, str) and name.startswith("pcc_ros."):  # (makeLogRecord: None)
            record.pcc_node = getattr(node, "name", name)
        return record

    return make


logging.setLogRecordFactory(_tagged_with_the_node(logging.getLogRecordFactory()))


def output_names(mode: str, with_completion: bool = False) -> list[str]:
    """The outputs a node of ``mode`` publishes; ``with_completion`` adds the completion
    outputs to a filter node's (``pcc replay --filter`` records both from one pipeline run)."""
    if mode not in MODES:
        raise ConfigError(f"node mode must be one of {MODES}, not {mode!r}")
    names = list(OUTPUTS[mode])
    if with_completion and mode != "completion":
        names = [*OUTPUTS["completion"], *names]
    return names


def qos_of(values: dict[str, Any], topic: str) -> QoS:
    """The :class:`QoS` of ``points``, ``detections`` or ``outputs`` from the node parameters."""
    return QoS(
        reliable=values[f"qos.{topic}.reliability"] == "reliable", depth=int(values[f"qos.{topic}.depth"])
    )


@dataclass
class SetResult:
    """Outcome of :meth:`NodeCore.set_parameters` (rclpy's ``SetParametersResult`` fields)."""

    successful: bool
    reason: str = ""


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
        outputs: the output topics (default names) to publish, default :func:`output_names` of
            ``mode``; ``pcc replay --filter`` asks for the completion outputs as well.
        on_result: called as ``on_result(result, cloud, detections)`` after each published
            frame (``detections`` as received, ``result`` in the scan frame): replay's summary,
            the demo and evaluation read the frames through it.
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
        outputs: list[str] | None = None,
        on_result=None,
    ) -> None:
        names = output_names(mode) if outputs is None else list(outputs)
        every = {**OUTPUTS["completion"], **OUTPUTS["filter"]}
        unknown = [n for n in names if n not in every]
        if unknown:
            raise ConfigError(f"unknown node output(s) {unknown}; known: {sorted(every)}")
        self.runtime, self.node_name, self.mode = runtime, node_name, mode
        self.log = runtime.get_logger()
        values = node_parameters(parameters)
        self.parameters = values
        config = pipeline_config(values)
        with working_for(self.log):  # a backend's load lines are this node's
            self.pipeline = pipeline or Pipeline(config)  # a missing/corrupt checkpoint fails here, loudly
        self.output_frame = str(values["output_frame"])
        self.pairer: StampPairer = StampPairer(
            slop_ns=int(float(values["sync_slop"]) * 1e9), queue_size=int(values["queue_size"])
        )
        self.slot: LatestSlot = LatestSlot(self.pairer.stats)
        self.frames = 0
        self.failures = 0
        self.first_failure = ""  # the reason of the first skipped frame (replay's summary names it)
        self.on_result = on_result
        self.no_transform = 0  # frames skipped because a transform was not available
        self.parameter_changes = 0
        self._parameter_lock = threading.Lock()
        # Arrival bookkeeping: scans that stop arriving while detections keep coming (a large
        # cloud the middleware drops) must show on /diagnostics, not look like an idle node.
        self.scans = 0
        self.detection_arrays = 0
        self.detections_without_scans = 0
        self.scans_stalled = False
        self._last_scan_ns: int | None = None
        self._first_detections_ns: int | None = None
        self._scan_timeout_ns = int(float(values["scan_timeout"]) * 1e9)
        if self._scan_timeout_ns <= 0:
            raise ConfigError(f"scan_timeout must be > 0, not {values['scan_timeout']}")
        self._no_transform_logged: set[tuple[str, str]] = set()
        self.decisions = dict.fromkeys(DECISIONS, 0)  # filter mode: totals
        #: detections skipped per reason ("other class", "invalid detection", ...), all frames
        self.skipped_totals: dict[str, int] = {}
        self._other_classes: set[str] = set()  # class ids outside `classes` already reported
        self._drops_seen = 0  # unpaired messages dropped, as last looked at (logged at 1, 10, 100 ...)
        self.last_decisions = dict(self.decisions)
        self.latency_ms: list[float] = []
        remap = remap or {}
        self.topics = {name: remap.get(name, name) for name in [*INPUTS, *names]}
        #: Default output name -> message type, in publishing order: the one topic table.
        self.outputs = {name: every[name] for name in names}
        #: Publishes detection messages: the pipeline keeps (and moves) the received ones for them.
        self._republishes_detections = any(name in DETECTION_OUTPUTS for name in names)

        self.publishers = {
            name: runtime.create_publisher(self.topics[name], msgtype, qos_of(values, "outputs"))
            for name, msgtype in self.outputs.items()
        }
        self.pub_diagnostics = runtime.create_publisher(
            DIAGNOSTICS_TOPIC, "diagnostic_msgs/msg/DiagnosticArray", RELIABLE
        )
        runtime.create_subscription(self.topics["points"], INPUTS["points"], self.on_cloud, qos_of(values, "points"))
        runtime.create_subscription(
            self.topics["detections"], INPUTS["detections"], self.on_detections, qos_of(values, "detections")
        )
        runtime.create_timer(1.0, self.publish_diagnostics)

        self.threaded = threaded
        self._running = threaded
        self._refreeze = threading.Event()  # set by a backend reload, served by the worker
        self._worker = None
        if threaded:
            self._worker = threading.Thread(target=self._work, name=f"{node_name}_worker", daemon=True)
            self._worker.start()
        self._warn_without_tf()
        freeze_long_lived()  # the loaded backend and the node's objects: no full collection walks them per frame
        self.log.info(
            f"{mode} node ready: backend={config.backend} classes={list(config.classes)} device={config.device}"
            + (f" output_frame={self.output_frame}" if self.output_frame else "")
        )

    def _warn_without_tf(self) -> None:
        """Say once, at start-up or when output_frame is set, that frames will be skipped without tf2."""
        if self.output_frame and not getattr(self.runtime, "has_tf", True):
            self.log.error(
                f"output_frame '{self.output_frame}' needs tf2_ros, which this runtime does not have (the ROS 2 "
                "wheels from PyPI do not ship it): every frame whose scan is not already in that frame is "
                "skipped and counted as frames_without_transform on /diagnostics. Install ROS 2 Jazzy's "
                "tf2_ros or leave output_frame empty."
            )

    # ------------------------------------------------------------- parameters

    def set_parameters(self, changes: dict[str, Any]) -> SetResult:
        """Validate and apply parameter changes while the node runs; all or nothing.

        The rclpy host calls this from its ``add_on_set_parameters_callback``. A change of
        the backend, checkpoint, device, precision or batch size loads the new backend
        first and swaps it in only when it loaded; thresholds, classes and the other
        pipeline parameters swap without a reload. The frame in flight finishes with the
        old pipeline; the node never stops serving. Refused (with the reason, nothing
        changed): unknown names, wrong types, values outside their range, read-only
        parameters (QoS, queue size), a backend that does not load.
        """
        specs = parameter_specs()
        changes = {k: v for k, v in changes.items() if k not in ("use_sim_time",)}
        with self._parameter_lock:
            try:
                unknown = unknown_parameters(changes)
                if unknown:
                    raise ConfigError(f"unknown parameter(s) {unknown}")
                checked = {name: check_value(specs[name], value) for name, value in changes.items()}
                changed = {n: v for n, v in checked.items() if v != self.parameters[n]}
                fixed = sorted(n for n in changed if specs[n].read_only)
                if fixed:
                    raise ConfigError(f"{fixed} cannot change while the node runs: restart the node")
                if not changed:
                    return SetResult(True, "")
                values = {**self.parameters, **changed}
                config = pipeline_config(values)
                old = self.pipeline
                reload = any(
                    n in changed for n in BACKEND_PARAMETERS
                ) or not isinstance(old, Pipeline)
                with working_for(self.log):
                    pipeline = Pipeline(config) if reload else Pipeline(config, completer=old.completer)
            except PccError as exc:
                self.log.warning(f"parameter change refused: {exc}")
                return SetResult(False, str(exc))
            self.pipeline = pipeline  # one reference swap: the worker picks it up with its next frame
            self.parameters = values
            self.output_frame = str(values["output_frame"])
            self.pairer.slop_ns = int(float(values["sync_slop"]) * 1e9)
            self.parameter_changes += 1
            if {"classes", "class_map"} & set(changed):
                self._other_classes = set()  # report the class ids the new setting leaves out
        if reload:
            del old
            if self.threaded:
                # The worker collects between two frames: here, a frame in flight on the old
                # backend would stall for the collection (50-70 ms) and still hold the backend,
                # which the freeze would then keep for good.
                self._refreeze.set()
            else:
                freeze_long_lived()  # the old backend is collected, the new one frozen
        summary = ", ".join(f"{n}={v!r}" for n, v in sorted(changed.items()))
        self.log.info(f"parameters changed: {summary}" + (" (backend reloaded)" if reload else ""))
        if "output_frame" in changed:
            self._warn_without_tf()
        return SetResult(True, "")

    # ------------------------------------------------------------- callbacks

    def on_cloud(self, msg) -> None:
        self.scans += 1
        self._last_scan_ns = self.runtime.now_ns()
        if self.scans_stalled:
            self.scans_stalled = False
            self.log.info("scans arrive again")
        self._pair(self.pairer.add_left, msg)

    def on_detections(self, msg) -> None:
        self.detection_arrays += 1
        now = self.runtime.now_ns()
        if self._first_detections_ns is None:
            self._first_detections_ns = now
        since = self._last_scan_ns if self._last_scan_ns is not None else self._first_detections_ns
        if now - since > self._scan_timeout_ns:
            self.detections_without_scans += 1
            if not self.scans_stalled:
                self.scans_stalled = True
                self.log.warning(
                    f"detections arrive but no scan on '{self.topics['points']}' for {(now - since) / 1e9:.1f} s: "
                    "large clouds dropped by the middleware? (docs/nodes.md, 'Large clouds')"
                )
        self._pair(self.pairer.add_right, msg)

    def _pair(self, add, msg) -> None:
        try:
            stamp = stamp_to_ns(msg.header.stamp)
        except (PccError, AttributeError) as exc:
            self.failures += 1
            self.log.warning(f"message without a usable header skipped: {exc}")
            return
        pair = add(stamp, msg)
        self._report_drops()
        if pair is None:
            return
        if self.threaded:
            self.slot.put(pair)
        else:
            self._process_logged(*pair)

    def _report_drops(self) -> None:
        """Log the 1st, 10th, 100th ... message the pairer drops unpaired, with why it found no
        partner (the nearest stamp the other stream sent): a detector that stamps with its own
        clock, or scans lost on the way, would otherwise only show as counters."""
        stats = self.pairer.stats
        total = stats.dropped_clouds + stats.dropped_detections
        if total == self._drops_seen:
            return
        due = worth_logging(total, previous=self._drops_seen)  # one call can drop several messages
        self._drops_seen = total
        if not due:
            return
        what, other = ("scan", "detections") if stats.last_drop_left else ("detections", "scan")
        gap = stats.last_drop_gap_ns
        if gap < 0:
            topic = self.topics["detections" if stats.last_drop_left else "points"]
            qos = "qos.detections.reliability" if stats.last_drop_left else "qos.points.reliability"
            near = (f"no {other} has arrived at all: check the topic ('{topic}', remapped?) and its QoS (a "
                    f"best-effort publisher never reaches a reliable reader: set {qos}: best_effort)")
        elif gap > self.pairer.slop_ns:
            near = f"the nearest {other} stamp seen lately was {gap / 1e6:.0f} ms away"
        else:  # its partner arrived, but paired with a closer message or after a newer pair
            near = f"a {other} stamp {gap / 1e6:.0f} ms away had paired with another message or came out of order"
        self.log.warning(
            f"{total} messages dropped unpaired so far ({stats.dropped_clouds} scans, {stats.dropped_detections} "
            f"detection arrays; dropped_clouds / dropped_detections on /diagnostics): the last, {what} stamped "
            f"{stats.last_drop_stamp_ns / 1e9:.3f}, found no {other} within sync_slop "
            f"{self.pairer.slop_ns / 1e9:g} s; {near}. A detector must copy the scan's header stamp (if it "
            "restamps, raise sync_slop); scans lost on the way: docs/nodes.md 'Large clouds'."
        )

    def _wanted_outputs(self) -> list[str]:
        """The outputs to build this frame: every data output, and a marker array only while
        something subscribes to it (RViz). The markers are most of the encode time with rclpy's
        message classes (about a thousand messages at 20 cars), and nobody reads them on a robot
        that is not being watched; a viewer that subscribes gets them from the next frame on."""
        return [name for name, pub in self.publishers.items()
                if name not in MARKER_OUTPUTS or pub.get_subscription_count() > 0]

    def _report_other_classes(self, labels: np.ndarray, classes) -> None:
        """Say once per class id that detections outside ``classes`` are passed over (a detector
        whose ids the node does not know would otherwise be silently ignored: nothing completed,
        nothing judged)."""
        if not len(labels) or len(self._other_classes) >= _REPORTED_CLASSES:
            return
        new = sorted({str(v) for v in labels[~class_mask(labels, classes)]} - self._other_classes)
        new = new[: _REPORTED_CLASSES - len(self._other_classes)]  # bounded within one frame too
        if not new:
            return
        self._other_classes.update(new)
        effect = "not completed" if self.mode == "completion" else "passed on unjudged"
        numeric = [v for v in new if integer_id(v) is not None]
        if numeric:
            self.log.warning(
                f"detections of class id(s) {numeric} are not in classes {list(classes)}: {effect}. Numeric ids "
                "come from the detector's class list: map them with class_map (OpenPCDet: '1:Car'; "
                "mmdetection3d nuScenes: '0:car', its KITTI 3-class model: '2:Car'; check your model's "
                "class names). Counted as skipped_other_class on /diagnostics"
            )
        if "" in new:  # no hypothesis at all: a single-class detector that leaves results empty?
            self.log.warning(
                f"detections without a class (no hypotheses in results) are not in classes {list(classes)}: "
                f"{effect}. A single-class vehicle detector that sends none: add '' to classes "
                "(classes: [Car, Van, '']). Counted as skipped_other_class on /diagnostics"
            )
        names = [v for v in new if v not in numeric and v != ""]
        if names:
            self.log.info(
                f"detections of class(es) {names} are not in classes {list(classes)}: {effect} (counted as "
                "skipped_other_class on /diagnostics; add a class to classes to include it)"
            )

    def _work(self) -> None:
        while self._running:
            if self._refreeze.is_set():  # a backend was reloaded: between frames, collect the old one
                self._refreeze.clear()
                freeze_long_lived()
            pair = self.slot.take(timeout=0.5)
            if pair is not None:
                self._process_logged(*pair)

    def _process_logged(self, cloud, detections) -> None:
        try:
            with working_for(self.log):  # the decoders' and the pipeline's lines are this node's
                self.process(cloud, detections)
        except PccError as exc:  # malformed input: log, skip, keep serving
            self._failed(str(exc))
            self.log.warning(f"skipped a frame: {exc}")
        except Exception as exc:  # a running node must not die on one frame
            self._failed(f"{type(exc).__name__}: {exc}")
            self.log.error(f"frame failed: {type(exc).__name__}: {exc}")

    def _failed(self, reason: str) -> None:
        self.failures += 1
        self.first_failure = self.first_failure or reason

    # ------------------------------------------------------------- work

    def process(self, cloud, detections) -> dict[str, Any] | None:
        """Run one pair through the pipeline and publish; returns the published messages (None: skipped)."""
        tic = time.perf_counter()
        pipeline, output_frame = self.pipeline, self.output_frame  # one consistent set per frame
        transform = None
        source, target = detections.header.frame_id, cloud.header.frame_id
        if source and not same_frame(source, target):  # detections in another frame: moved once, after decoding
            transform = self._lookup(target, source, stamp_to_ns(detections.header.stamp))
            if transform is None:
                return None
        result, originals = pipeline.process_messages(cloud, detections, transform=transform,
                                                      with_originals=self._republishes_detections)
        header = cloud.header
        if output_frame and not same_frame(output_frame, result.frame_id):
            moved = self._to_output_frame(result, originals, output_frame)
            if moved is None:
                return None
            result, originals = moved
            header = make_header(output_frame, result.stamp_ns, self.runtime.classes)
        outputs = build_outputs(result, originals, self.runtime.classes, detections_header=header,
                                names=self._wanted_outputs())
        for name, msg in outputs.items():
            self.publishers[name].publish(msg)
        self.frames += 1
        if self.mode == "filter":
            self.last_decisions = decision_counts(result.status, result.skipped.get("invalid detection", 0))
            for k, v in self.last_decisions.items():
                self.decisions[k] += v
        self.latency_ms.append((time.perf_counter() - tic) * 1e3)
        del self.latency_ms[:-200]
        if result.skipped:
            self.log.debug(f"frame {result.stamp_ns}: skipped {result.skipped}")
            for reason, n in result.skipped.items():
                self.skipped_totals[reason] = self.skipped_totals.get(reason, 0) + n
        self._report_other_classes(result.detections.label, pipeline.config.classes)
        if self.on_result is not None:
            self.on_result(result, cloud, detections)
        return outputs

    def _lookup(self, target: str, source: str, stamp_ns: int):
        """The runtime's transform, or None (counted; the reason logged once per frame pair)."""
        # tf2 in ROS 2 refuses frame ids with a leading '/' (ROS 1 drivers, converted bags): strip it
        tf = self.runtime.lookup_transform(frame_name(target), frame_name(source), stamp_ns)
        if tf is None:
            self.no_transform += 1
            self._failed(f"no transform '{source}' -> '{target}'")
            if (source, target) not in self._no_transform_logged:  # once per frame pair, then counted
                self._no_transform_logged.add((source, target))
                self.log.warning(
                    f"no transform '{source}' -> '{target}': such frames are skipped "
                    "(counted on /diagnostics as frames_without_transform)"
                )
        return tf

    def _to_output_frame(self, result: FrameResult, originals, frame: str):
        """The frame's result and detection messages re-expressed in ``frame``, or None (no transform)."""
        tf = self._lookup(frame, result.frame_id, result.stamp_ns)
        if tf is None:
            return None
        matrix = tf.matrix()
        points = (result.completed_points.astype(np.float64) @ matrix[:3, :3].T + matrix[:3, 3]).astype(np.float32)
        moved = replace(
            result, frame_id=frame, detections=transform_boxes(result.detections, matrix), completed_points=points,
            unjudged_originals=transform_detections(result.unjudged_originals, tf, frame),
        )
        return moved, None if originals is None else transform_detections(originals, tf, frame)

    # ------------------------------------------------------------- diagnostics

    def diagnostics_values(self) -> dict[str, str]:
        """The key/values of the node's diagnostics status (counters and latency percentiles)."""
        stats = self.pairer.stats
        latency = np.array(self.latency_ms) if self.latency_ms else np.zeros(1)
        values = {
            "frames": self.frames,
            "failed_frames": self.failures,
            "paired": stats.paired,
            "dropped_clouds": stats.dropped_clouds,
            "dropped_detections": stats.dropped_detections,
            "dropped_pairs_newest_wins": stats.dropped_pairs,
            "frames_without_transform": self.no_transform,
            "parameter_changes": self.parameter_changes,
            "backend": self.parameters["backend"],
            "scans_received": self.scans,
            "detections_received": self.detection_arrays,
            "detections_without_scans": self.detections_without_scans,
            "last_unpaired_gap_ms": f"{stats.last_drop_gap_ns / 1e6:.1f}" if stats.last_drop_gap_ns >= 0 else "-",
            **{f"skipped_{reason.replace(' ', '_')}": n for reason, n in sorted(self.skipped_totals.items())},
            "latency_p50_ms": f"{np.percentile(latency, 50):.1f}",
            "latency_p95_ms": f"{np.percentile(latency, 95):.1f}",
        }
        if self.mode == "filter":
            for k in DECISIONS:
                values[f"detections_{k}"] = self.decisions[k]
                values[f"last_frame_{k}"] = self.last_decisions[k]
        return {k: str(v) for k, v in values.items()}

    def diagnostics_message(self):
        """A ``diagnostic_msgs/DiagnosticArray`` of the runtime's class flavour (level WARN after failures)."""
        classes = self.runtime.classes
        failed = self.failures
        level = 1 if failed or self.scans_stalled else 0
        message = f"{self.frames} frames"
        if self.scans_stalled:
            message += f"; detections arrive but no scan for more than {self._scan_timeout_ns / 1e9:g} s"
        status = new_message(
            "diagnostic_msgs/msg/DiagnosticStatus",
            classes,
            level=bytes([level]) if _byte_is_bytes(classes) else level,
            name=f"pcc_ros: {self.node_name}",
            message=message,
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
    return not is_rosbags_class(classes("diagnostic_msgs/msg/DiagnosticStatus"))
