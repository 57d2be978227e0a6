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
from pcc_ros.pipeline.config import BACKEND_PARAMETERS, changed_parameters, node_parameters, pipeline_config
from pcc_ros.pipeline.core import FrameResult, Pipeline, needs_completion
from pcc_ros.pipeline.filter import DECISIONS, decision_counts
from pcc_ros.pipeline.outputs import DETECTION_OUTPUTS, MARKER_OUTPUTS, build_outputs
from pcc_ros.runtime.base import RELIABLE, QoS, Runtime
from pcc_ros.runtime.diagnostics import (
    Health,
    node_status,
    node_values,
    report_other_classes,
    silent_topic_hint,
    unpaired_message,
)
from pcc_ros.runtime.heap import freeze_long_lived
from pcc_ros.runtime.pairing import LatestSlot, StampPairer
from pcc_ros.runtime.tfwait import POLL_S, FrameTransforms, TransformWait, frame_transforms

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
#: A clock that moves back by more than this is a jump (a looped bag, a reset simulator).
JUMP_BACK_NS = 1_000_000
#: How long stopping waits for the worker's frame in flight. A frame that runs longer is never
#: published (the publish lock, see :meth:`NodeCore.shutdown`); the wait keeps the worker from
#: still running inference while a process that is exiting tears the interpreter down under it.
STOP_WAIT_S = 10.0


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


def pipeline_stages(names) -> dict[str, bool]:
    """The pipeline stages a node publishing ``names`` runs (:class:`Pipeline`'s ``completes`` /
    ``filters``): each node computes what its outputs need, no more (the filter rule may still
    ask for the completions: :func:`~pcc_ros.pipeline.core.needs_completion`)."""
    return {"completes": any(n in OUTPUTS["completion"] for n in names),
            "filters": any(n in OUTPUTS["filter"] for n in names)}


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
        connect: create the publishers, subscriptions, timer and worker now (a plain node);
            ``False`` loads and checks only, and :meth:`connect` serves later (a managed node's
            ``configure``, then ``activate``).
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
        connect: bool = True,
    ) -> None:
        names = output_names(mode) if outputs is None else list(outputs)
        every = {**OUTPUTS["completion"], **OUTPUTS["filter"]}
        unknown = [n for n in names if n not in every]
        if unknown:
            raise ConfigError(f"unknown node output(s) {unknown}; known: {sorted(every)}")
        self.runtime, self.node_name, self.mode = runtime, node_name, mode
        self.log = runtime.get_logger()
        with working_for(self.log):  # the parameters' and a backend's load lines are this node's
            values = node_parameters(parameters)
        self.parameters = values
        config = pipeline_config(values)
        #: the stages the outputs need (a filter node whose rule gives the shape no weight runs no network)
        self.stages = pipeline_stages(names)
        with working_for(self.log):  # a backend's load lines are this node's
            self.pipeline = pipeline or Pipeline(config, **self.stages)  # a missing/corrupt checkpoint fails here
        self.output_frame = str(values["output_frame"])
        self.pairer: StampPairer = StampPairer(
            slop_ns=int(float(values["sync_slop"]) * 1e9), queue_size=int(values["queue_size"])
        )
        self.slot: LatestSlot = LatestSlot(self.pairer.stats)
        self.frames = 0
        self.failures = 0
        self.first_failure = ""  # the reason of the first skipped frame (replay's summary names it)
        self.on_result = on_result
        self.no_transform = 0  # frames dropped because a transform did not arrive within tf_timeout
        self.tf_wait = TransformWait(float(values["tf_timeout"]))
        self.time_jumps = 0
        self._clock_ns: int | None = None  # the node clock as last seen (a jump back resets the node)
        self._clock_lock = threading.Lock()
        self.last_missing_transform = ""  # the last transform a dropped frame lacked (diagnostics' reason)
        self._tf_gap = False  # frames were dropped since the last frame whose transforms resolved
        self.tf_recoveries = 0
        self.health = Health()
        self.parameter_changes = 0
        self._parameter_lock = threading.Lock()
        # Arrival bookkeeping: scans that stop arriving while detections keep coming (a large
        # cloud the middleware drops) must show on /diagnostics, not look like an idle node.
        self.scans = 0
        self.detection_arrays = 0
        self.detections_without_scans = 0
        self.scans_stalled = False
        self._last_scan_ns: int | None = None
        self.last_detections_ns: int | None = None
        self._detections_since: int | None = None  # detections arriving without a long pause since
        self.scan_timeout_ns = int(float(values["scan_timeout"]) * 1e9)
        if self.scan_timeout_ns <= 0:
            raise ConfigError(f"scan_timeout must be > 0, not {values['scan_timeout']}")
        self._no_transform_logged: set[str] = set()
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

        self.publishers: dict[str, Any] = {}
        self.pub_diagnostics = None
        self.threaded = threaded
        self._running = False
        #: Held while a frame's messages go out and while serving stops: nothing is published
        #: on a publisher the runtime is about to destroy.
        self._publish_lock = threading.Lock()
        self._refreeze = threading.Event()  # set by a backend reload, served by the worker
        self._worker = None
        on_jump = getattr(runtime, "on_clock_jump", None)
        if on_jump is not None:  # the jump seen as /clock moves, before the new timeline's messages
            on_jump(self._watch_clock)
        self._warn_without_tf()
        freeze_long_lived()  # the loaded backend and the node's objects: no full collection walks them per frame
        if connect:
            self.connect()

    def connect(self) -> None:
        """Serve: create the output publishers, the input subscriptions, the diagnostics timer
        and the worker (a managed node's ``activate``; a plain node's start)."""
        runtime, values = self.runtime, self.parameters
        self.publishers = {
            name: runtime.create_publisher(self.topics[name], msgtype, qos_of(values, "outputs"))
            for name, msgtype in self.outputs.items()
        }
        self.pub_diagnostics = runtime.create_publisher(
            DIAGNOSTICS_TOPIC, "diagnostic_msgs/msg/DiagnosticArray", RELIABLE
        )
        subs = {
            "points": runtime.create_subscription(
                self.topics["points"], INPUTS["points"], self.on_cloud, qos_of(values, "points")),
            "detections": runtime.create_subscription(
                self.topics["detections"], INPUTS["detections"], self.on_detections, qos_of(values, "detections")),
        }
        #: The inputs' names as the graph knows them (remapped, in the namespace): what warnings name.
        self.resolved = {name: str(getattr(sub, "topic_name", "") or self.topics[name]) for name, sub in subs.items()}
        runtime.create_timer(1.0, self.publish_diagnostics)
        self._running = self.threaded
        if self.threaded:
            self.slot = LatestSlot(self.pairer.stats)
            self._worker = threading.Thread(target=self._work, name=f"{self.node_name}_worker", daemon=True)
            self._worker.start()
        config = self.pipeline.config
        self.log.info(
            f"{self.mode} node ready: backend={config.backend if self.pipeline.completes else '(none: no completion)'} "
            f"classes={list(config.classes)} device={config.device}"
            + (f" output_frame={self.output_frame}" if self.output_frame else "")
        )

    def _warn_without_tf(self) -> None:
        """Say once, at start-up or when output_frame is set, that frames will be skipped without tf2."""
        if self.output_frame and not getattr(self.runtime, "has_tf", True):
            self.log.error(
                f"output_frame '{self.output_frame}' needs transforms, which this runtime cannot look up (neither "
                "tf2_ros nor tf2_msgs is installed): every frame whose scan is not already in that frame is "
                "skipped and counted as frames_without_transform on /diagnostics. Run `make setup` (builds "
                "tf2_msgs into the venv), use a ROS 2 Jazzy install, or leave output_frame empty."
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
        changes = {k: v for k, v in changes.items() if k not in ("use_sim_time",)}
        with self._parameter_lock:
            try:
                changed = changed_parameters(self.parameters, changes)
                if not changed:
                    return SetResult(True, "")
                values = {**self.parameters, **changed}
                config = pipeline_config(values)
                old = self.pipeline
                reload = (any(n in changed for n in BACKEND_PARAMETERS) or not isinstance(old, Pipeline)
                          or (needs_completion(config, **self.stages) and old.completer is None))
                with working_for(self.log):
                    pipeline = Pipeline(config, completer=None if reload else old.completer, **self.stages)
            except PccError as exc:
                self.log.warning(f"parameter change refused: {exc}")
                return SetResult(False, str(exc))
            self.pipeline = pipeline  # one reference swap: the worker picks it up with its next frame
            self.parameters = values
            self.output_frame = str(values["output_frame"])
            self.pairer.slop_ns = int(float(values["sync_slop"]) * 1e9)
            self.tf_wait.timeout_s = float(values["tf_timeout"])
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

    def _watch_clock(self) -> int:
        """The node clock now; a jump back (under ``use_sim_time``: a looped bag, a reset simulator)
        resets the node to serve the new timeline."""
        with self._clock_lock:  # callbacks and the timer may run on different threads: read in order
            now = self.runtime.now_ns()
            last, self._clock_ns = self._clock_ns, now
            if last is not None and now < last - JUMP_BACK_NS:
                self._jumped_back(last, now)
        return now

    def _jumped_back(self, last_ns: int, now_ns: int) -> None:
        """Pairing queues, the pending pair, held frames and tf's dynamic transforms belong to the old
        timeline (the same stamps come again, with other poses): all are forgotten, as tf2 clears
        its buffer on such a jump; static transforms stay."""
        self.time_jumps += 1
        self.pairer.clear()
        self.slot.take(timeout=0)
        held = self.tf_wait.clear()
        reset = getattr(self.runtime, "reset_transforms", None)
        if reset is not None:
            reset()
        self._last_scan_ns = self.last_detections_ns = self._detections_since = None
        self.scans_stalled = False
        if worth_logging(self.time_jumps):
            self.log.warning(
                f"clock jumped back from {last_ns / 1e9:.3f} s to {now_ns / 1e9:.3f} s (a looped bag or a reset "
                f"simulator under use_sim_time): pairing queues, {held} held frame(s) and the tf buffer's dynamic "
                f"transforms reset; serving the new timeline (jump {self.time_jumps}: time_jumps_back on /diagnostics)"
            )

    def on_cloud(self, msg) -> None:
        self.scans += 1
        self._last_scan_ns = self._watch_clock()
        if self.scans_stalled:
            self.scans_stalled = False
            self.log.info("scans arrive again")
        self._pair(self.pairer.add_left, msg)

    def on_detections(self, msg) -> None:
        self.detection_arrays += 1
        now = self._watch_clock()
        if self.last_detections_ns is None or now - self.last_detections_ns > self.scan_timeout_ns:
            self._detections_since = now  # (re)started after a pause: a publisher that idled is no stall
        self.last_detections_ns = now
        since = max(self._last_scan_ns or 0, self._detections_since)
        if now - since > self.scan_timeout_ns:
            self.detections_without_scans += 1
            if not self.scans_stalled:
                self.scans_stalled = True
                hint = silent_topic_hint(self.runtime, self.resolved["points"], "qos.points.reliability",
                                         self.parameters["qos.points.reliability"])
                self.log.warning(f"detections arrive but no scan on '{self.resolved['points']}' for "
                                 f"{(now - since) / 1e9:.1f} s: {hint}")
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
        name = "detections" if stats.last_drop_left else "points"  # the input that sent nothing to pair with
        self.log.warning(unpaired_message(stats, self.pairer.slop_ns, lambda: silent_topic_hint(
            self.runtime, self.resolved[name], f"qos.{name}.reliability", self.parameters[f"qos.{name}.reliability"])))

    def _wanted_outputs(self) -> list[str]:
        """The outputs to build this frame: every data output, and a marker array only while
        something subscribes to it (RViz). The markers are most of the encode time with rclpy's
        message classes (about a thousand messages at 20 cars), and nobody reads them on a robot
        that is not being watched; a viewer that subscribes gets them from the next frame on."""
        return [name for name, pub in self.publishers.items()
                if name not in MARKER_OUTPUTS or pub.get_subscription_count() > 0]

    def _work(self) -> None:
        while self._running:
            if self._refreeze.is_set():  # a backend was reloaded: between frames, collect the old one
                self._refreeze.clear()
                freeze_long_lived()
            pair = self.slot.take(timeout=POLL_S if len(self.tf_wait) else 0.5)
            if pair is not None:
                for old in self.tf_wait.add(pair):  # over the hold's capacity: the oldest goes
                    self._dropped_without_transform(self._resolve(old)[1] or "(held frames over capacity)")
            if len(self.tf_wait):
                ready, dropped = self.tf_wait.release(self._resolve)
                for _, missing in dropped:
                    self._dropped_without_transform(missing)
                for (cloud, detections), transforms in ready:
                    self._process_logged(cloud, detections, transforms)

    def _resolve(self, pair) -> tuple[FrameTransforms | None, str]:
        """The transforms ``pair`` needs, or ``(None, what is missing)``; a message too malformed to
        say goes on to :meth:`process`, whose error names it."""
        try:
            return frame_transforms(self.runtime, *pair, self.output_frame)
        except Exception:
            return FrameTransforms(output_frame=self.output_frame), ""

    def _process_logged(self, cloud, detections, transforms: FrameTransforms | None = None) -> None:
        try:
            with working_for(self.log):  # the decoders' and the pipeline's lines are this node's
                self.process(cloud, detections, transforms)
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

    def process(self, cloud, detections, transforms: FrameTransforms | None = None) -> dict[str, Any] | None:
        """Run one pair through the pipeline and publish; returns the published messages (None: skipped).

        ``transforms``: looked up already (the worker held the frame until they arrived); by
        default looked up now, and a frame whose transform is unknown is dropped and counted."""
        tic = time.perf_counter()
        pipeline = self.pipeline  # one consistent set per frame
        if transforms is None:
            transforms, missing = frame_transforms(self.runtime, cloud, detections, self.output_frame)
            if transforms is None:
                self._dropped_without_transform(missing)
                return None
        if self._tf_gap and (transforms.detections is not None or transforms.output is not None):
            self._tf_gap = False
            self.tf_recoveries += 1  # tf that flaps: said at the 1st, 10th, 100th ... recovery
            if worth_logging(self.tf_recoveries):
                self.log.info(f"transforms arrive again ({self.no_transform} frame(s) dropped without one so far)")
        result, originals = pipeline.process_messages(cloud, detections, transform=transforms.detections,
                                                      with_originals=self._republishes_detections)
        header = cloud.header
        if transforms.output is not None:
            result, originals = self._to_output_frame(result, originals, transforms.output_frame, transforms.output)
            header = make_header(transforms.output_frame, result.stamp_ns, self.runtime.classes)
        outputs = build_outputs(result, originals, self.runtime.classes, detections_header=header,
                                names=self._wanted_outputs())
        with self._publish_lock:
            if not self.publishers:  # stopped serving (deactivated, shut down) while this frame ran
                return None
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
        report_other_classes(self.log, self.mode, result.detections.label, pipeline.config.classes,
                             self._other_classes)
        if self.on_result is not None:
            self.on_result(result, cloud, detections)
        return outputs

    def _dropped_without_transform(self, missing: str) -> None:
        """Count a frame dropped for want of a transform; log the 1st, 10th, 100th ... and each new pair of frames."""
        self.no_transform += 1
        self._tf_gap = True
        self.last_missing_transform = missing
        self._failed(f"no transform {missing}")
        if missing not in self._no_transform_logged and len(self._no_transform_logged) < 64:  # hostile ids: bounded
            self._no_transform_logged.add(missing)
        elif not worth_logging(self.no_transform):
            return
        source = getattr(getattr(self.runtime, "tf", None), "name", "the runtime's transforms")
        wait = f"within tf_timeout {self.tf_wait.timeout_s:g} s" if self.threaded else "(offline: nothing more comes)"
        self.log.warning(
            f"no transform {missing} at the frame's stamp {wait} ({source}): frame dropped, never processed in "
            f"the wrong frame ({self.no_transform} so far: frames_without_transform on /diagnostics)"
        )

    def _to_output_frame(self, result: FrameResult, originals, frame: str, tf):
        """The frame's result and detection messages re-expressed in ``frame`` (``tf``: ``frame`` <- scan)."""
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
        return node_values(self)

    def diagnostics_message(self):
        """A ``diagnostic_msgs/DiagnosticArray`` of the runtime's class flavour: WARN, with the reasons,
        while lost work was counted lately (:mod:`pcc_ros.runtime.diagnostics`) or scans stall."""
        return node_status(self)

    def publish_diagnostics(self) -> None:
        publisher = self.pub_diagnostics
        if publisher is None:  # not serving
            return
        try:
            self._watch_clock()
            publisher.publish(self.diagnostics_message())
        except Exception as exc:  # diagnostics must never take the node down
            self.log.error(f"diagnostics failed: {type(exc).__name__}: {exc}")

    def shutdown(self) -> None:
        """Stop serving: the worker ends (a pending pair is dropped) and nothing is published any
        more; the backend stays loaded (a managed node's ``deactivate``: :meth:`connect` serves
        again). The runtime closes its own entities."""
        self._running = False
        self.slot.close()
        if self._worker is not None:
            self._worker.join(timeout=STOP_WAIT_S)
            if self._worker.is_alive():
                self.log.warning(f"the frame in flight still runs after {STOP_WAIT_S:g} s: its results are dropped")
            self._worker = None
        with self._publish_lock:  # a frame still in flight finds no publisher from here on
            self.publishers = {}
            self.pub_diagnostics = None

