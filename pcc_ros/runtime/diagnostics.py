"""What a node says about itself: ``/diagnostics`` that tells the truth, and the hints in its warnings.

A status that stays OK while frames are dropped for want of a transform, or that blames QoS
for a topic nobody publishes on, sends whoever reads it the wrong way. So:

* :class:`Health` raises the level to WARN while a counter that means lost work moved within
  the last :data:`WINDOW_NS` of node time (frames dropped for a missing transform, failed
  frames, invalid or capped boxes, detections the filter could not judge, a scan without a
  point, a clock that jumped back), with the reason and the count in the status message; back
  to OK once it stops.
  Skips that are the configuration working as meant (other classes, cars with too few points)
  are reported as values only.
* :func:`silent_topic_hint` names the resolved topic (after remapping), says when nobody
  publishes on it before suspecting QoS or the middleware, and never suggests the setting
  already in force.
"""

from __future__ import annotations

from collections import deque
from typing import Any

import numpy as np

from pcc_ros.msg.stamps import make_header
from pcc_ros.msg.typestore import is_rosbags_class, new_message
from pcc_ros.pipeline.config import integer_id
from pcc_ros.types import class_mask

#: How long a moved counter keeps the status at WARN (node time).
WINDOW_NS = 10_000_000_000
OK, WARN = 0, 1
#: At most this many distinct class ids outside ``classes`` are reported (hostile labels stay bounded).
REPORTED_CLASSES = 64

#: Counters whose growth is lost work -> how the status message says it (``{n}``: the growth).
WARN_REASONS = {
    "frames_without_transform": "{n} frame(s) dropped: no transform {missing} within tf_timeout",
    "failed_frames_other": "{n} frame(s) failed ({first})",
    "skipped_invalid_detection": "{n} invalid detection(s) skipped",
    "skipped_over_max_instances": "{n} detection(s) over max_instances not completed",
    "skipped_over_max_crop_work": "{n} detection(s) over max_crop_work not completed",
    "skipped_unjudged_over_evidence_work": "{n} detection(s) over the evidence work bound unjudged",
    "detections_unjudged": "{n} detection(s) could not be judged",
    "skipped_empty_scan": "{n} detection(s) of a scan without a finite point",
    "time_jumps_back": "clock jumped back {n} time(s): pairing, queues and tf reset",
}


class Health:
    """Counters at each diagnostics tick over the last :data:`WINDOW_NS`; which grew, and by how much."""

    def __init__(self, window_ns: int = WINDOW_NS) -> None:
        self.window_ns = int(window_ns)
        self._ticks: deque[tuple[int, dict[str, int]]] = deque()

    def recent(self, now_ns: int, counters: dict[str, int]) -> dict[str, int]:
        """Growth of each counter since the oldest tick within the window (only those that grew)."""
        if self._ticks and now_ns < self._ticks[-1][0]:  # the clock jumped back: the window restarts here,
            self._ticks = deque([(now_ns, self._ticks[-1][1])])  # from the counters as they were
        while self._ticks and now_ns - self._ticks[0][0] > self.window_ns:
            self._ticks.popleft()
        base = self._ticks[0][1] if self._ticks else {}
        self._ticks.append((now_ns, dict(counters)))
        grown = {k: v - base.get(k, 0) for k, v in counters.items()}
        return {k: n for k, n in grown.items() if n > 0}


def status_level_and_message(frames: int, grown: dict[str, int], context: dict[str, str],
                             stalled: str = "") -> tuple[int, str]:
    """The status level and its message: ``"<frames> frames"``, then each reason for WARN."""
    reasons = [WARN_REASONS[k].format(n=n, **context) for k, n in grown.items() if k in WARN_REASONS]
    if reasons:
        reasons[-1] += f" (last {WINDOW_NS // 1_000_000_000} s)"
    if stalled:
        reasons.insert(0, stalled)
    return (WARN if reasons else OK), f"{frames} frames" + "".join(f"; {r}" for r in reasons)


def diagnostic_array(classes, node_name: str, level: int, message: str, values: dict[str, str], now_ns: int):
    """A ``diagnostic_msgs/DiagnosticArray`` of the runtime's class flavour with one status."""
    status = new_message(
        "diagnostic_msgs/msg/DiagnosticStatus",
        classes,
        level=bytes([level]) if not is_rosbags_class(classes("diagnostic_msgs/msg/DiagnosticStatus")) else level,
        name=f"pcc_ros: {node_name}",
        message=message,
        hardware_id="pcc_ros",
        values=[new_message("diagnostic_msgs/msg/KeyValue", classes, key=k, value=v) for k, v in values.items()],
    )
    header = make_header("", now_ns, classes)
    return new_message("diagnostic_msgs/msg/DiagnosticArray", classes, header=header, status=[status])


def silent_topic_hint(runtime: Any, topic: str, qos_parameter: str, reliability: str) -> str:
    """Why nothing arrives on ``topic`` (resolved): nobody publishes on it, or (only where the
    reader is reliable, so a best-effort publisher cannot reach it) its QoS, else the middleware."""
    try:
        publishers = int(runtime.count_publishers(topic))
    except Exception:  # a runtime without graph introspection: say what is possible
        publishers = -1
    if publishers == 0:
        return f"nobody publishes on '{topic}' (remap the input to the topic your driver or detector uses)"
    who = f"{publishers} publisher(s) on '{topic}'" if publishers > 0 else f"'{topic}'"
    if reliability == "reliable":
        return (f"{who} but nothing arrives: a best-effort publisher never reaches this reliable reader "
                f"(set {qos_parameter}: best_effort)")
    return (f"{who} but nothing arrives: messages lost in the middleware (large clouds: docs/nodes.md "
            "'Large clouds')")


def node_values(core: Any) -> dict[str, str]:
    """The key/values of a :class:`~pcc_ros.runtime.node.NodeCore`'s status (counters, latency percentiles)."""
    stats = core.pairer.stats
    latency = np.array(core.latency_ms) if core.latency_ms else np.zeros(1)
    values = {
        "frames": core.frames,
        "failed_frames": core.failures,
        "paired": stats.paired,
        "dropped_clouds": stats.dropped_clouds,
        "dropped_detections": stats.dropped_detections,
        "dropped_pairs_newest_wins": stats.dropped_pairs,
        "frames_without_transform": core.no_transform,
        "frames_waiting_for_transform": len(core.tf_wait),
        "frames_released_after_waiting": core.tf_wait.released_late,
        "time_jumps_back": core.time_jumps,
        "parameter_changes": core.parameter_changes,
        "backend": core.parameters["backend"],
        "scans_received": core.scans,
        "detections_received": core.detection_arrays,
        "detections_without_scans": core.detections_without_scans,
        "last_unpaired_gap_ms": f"{stats.last_drop_gap_ns / 1e6:.1f}" if stats.last_drop_gap_ns >= 0 else "-",
        **{f"skipped_{reason.replace(' ', '_')}": n for reason, n in sorted(core.skipped_totals.items())},
        "latency_p50_ms": f"{np.percentile(latency, 50):.1f}",
        "latency_p95_ms": f"{np.percentile(latency, 95):.1f}",
    }
    if core.mode == "filter":
        pipeline = getattr(core, "pipeline", None)
        in_force = getattr(pipeline, "threshold_in_force", None)
        if in_force is not None:  # the evidence rule's threshold, and the preset the beam model matched
            values["reject_threshold_in_force"] = f"{in_force[1]:.4f}"
            values["sensor_preset_matched"] = in_force[0] or "-"
            height = getattr(getattr(pipeline, "beam_model", None), "mount_height", None)
            values["sensor_height_m"] = "-" if height is None else f"{height:.2f}"
        for k in core.decisions:
            values[f"detections_{k}"] = core.decisions[k]
            values[f"last_frame_{k}"] = core.last_decisions[k]
    return {k: str(v) for k, v in values.items()}


def node_status(core: Any):
    """A node core's ``DiagnosticArray``: WARN with the reasons while lost work was counted within
    the window, or while detections arrive and scans do not (cleared once detections stop too:
    an idle graph has nothing waiting to be paired)."""
    now = core.runtime.now_ns()
    if core.scans_stalled and now - (core.last_detections_ns or now) > core.scan_timeout_ns:
        core.scans_stalled = False
    values = node_values(core)
    counters = {k: int(v) for k, v in values.items() if k.startswith("skipped_") or k in (
        "frames_without_transform", "time_jumps_back", "detections_unjudged")}
    counters["failed_frames_other"] = core.failures - core.no_transform
    grown = core.health.recent(now, counters)
    context = {"missing": core.last_missing_transform or "?", "first": core.first_failure or "?"}
    stalled = (f"detections arrive but no scan on '{core.resolved['points']}' for more than "
               f"{core.scan_timeout_ns / 1e9:g} s") if core.scans_stalled else ""
    level, message = status_level_and_message(core.frames, grown, context, stalled)
    return diagnostic_array(core.runtime.classes, core.node_name, level, message, values, now)


def report_other_classes(log: Any, mode: str, labels: np.ndarray, classes, seen: set[str]) -> None:
    """Say once per class id that detections outside ``classes`` are passed over (a detector whose
    ids the node does not know would otherwise be silently ignored: nothing completed, nothing
    judged); ``seen`` holds the ids already reported."""
    if not len(labels) or len(seen) >= REPORTED_CLASSES:
        return
    new = sorted({str(v) for v in labels[~class_mask(labels, classes)]} - seen)
    new = new[: REPORTED_CLASSES - len(seen)]  # bounded within one frame too
    if not new:
        return
    seen.update(new)
    effect = "not completed" if mode == "completion" else "passed on unjudged"
    numeric = [v for v in new if integer_id(v) is not None]
    if numeric:
        log.warning(
            f"detections of class id(s) {numeric} are not in classes {list(classes)}: {effect}. Numeric ids "
            "come from the detector's class list: map them with class_map (OpenPCDet: '1:Car'; "
            "mmdetection3d nuScenes: '0:car', its KITTI 3-class model: '2:Car'; check your model's "
            "class names). Counted as skipped_other_class on /diagnostics"
        )
    if "" in new:  # no hypothesis at all: a single-class detector that leaves results empty?
        log.warning(
            f"detections without a class (no hypotheses in results) are not in classes {list(classes)}: "
            f"{effect}. A single-class vehicle detector that sends none: add '' to classes "
            "(classes: [Car, Van, '']). Counted as skipped_other_class on /diagnostics"
        )
    names = [v for v in new if v not in numeric and v != ""]
    if names:
        log.info(
            f"detections of class(es) {names} are not in classes {list(classes)}: {effect} (counted as "
            "skipped_other_class on /diagnostics; add a class to classes to include it)"
        )


def unpaired_message(stats: Any, slop_ns: int, silent_hint) -> str:
    """The warning for messages the pairer dropped unpaired (:class:`~pcc_ros.runtime.pairing.SyncStats`),
    with why the last found no partner: the nearest stamp the other stream sent, or (none arrived
    at all) ``silent_hint()`` about the silent input."""
    what, other = ("scan", "detections") if stats.last_drop_left else ("detections", "scan")
    gap = stats.last_drop_gap_ns
    if gap < 0:
        near = f"no {other} has arrived at all: {silent_hint()}"
    elif gap > slop_ns:
        near = f"the nearest {other} stamp seen lately was {gap / 1e6:.0f} ms away"
    else:  # its partner arrived, but paired with a closer message or after a newer pair
        near = f"a {other} stamp {gap / 1e6:.0f} ms away had paired with another message or came out of order"
    total = stats.dropped_clouds + stats.dropped_detections
    return (f"{total} messages dropped unpaired so far ({stats.dropped_clouds} scans, {stats.dropped_detections} "
            f"detection arrays; dropped_clouds / dropped_detections on /diagnostics): the last, {what} stamped "
            f"{stats.last_drop_stamp_ns / 1e9:.3f}, found no {other} within sync_slop {slop_ns / 1e9:g} s; {near}. "
            "A detector must copy the scan's header stamp (if it restamps, raise sync_slop); scans lost on the "
            "way: docs/nodes.md 'Large clouds'.")
