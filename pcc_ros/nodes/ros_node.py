"""The rclpy runtime: a thin adapter that hosts :class:`pcc_ros.runtime.node.NodeCore` in an rclpy node.

Thin by design (ros2/demos style): ROS parameters in, the node core does the rest —
pairing, the newest-wins worker, the pipeline, publishing, diagnostics values — exactly
as in-process (:mod:`pcc_ros.runtime.local`, tests and ``pcc replay``). This module and
its siblings are the only ones that import rclpy.
"""

from __future__ import annotations

import contextlib
import functools
import importlib
import itertools
import logging
import re
import sys

import rclpy
from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    ParameterType,
    SetParametersResult,
)
from rclpy.clock import JumpThreshold
from rclpy.duration import Duration
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.qos_overriding_options import InvalidQosOverridesError, QoSOverridingOptions
from rclpy.utilities import remove_ros_args

from pcc_ros.errors import ConfigError, PccError
from pcc_ros.nodes.tf_listener import transform_source
from pcc_ros.pipeline.config import ParameterSpec, parameter_table, read_parameters, unknown_parameters
from pcc_ros.runtime.base import QoS, Transform
from pcc_ros.runtime.node import DIAGNOSTICS_TOPIC, INPUTS, NodeCore, node_at_work

_TYPES = {
    "bool": ParameterType.PARAMETER_BOOL,
    "integer": ParameterType.PARAMETER_INTEGER,
    "double": ParameterType.PARAMETER_DOUBLE,
    "string": ParameterType.PARAMETER_STRING,
    "string_array": ParameterType.PARAMETER_STRING_ARRAY,
}


@functools.cache
def rclpy_classes(name: str) -> type:
    """Message class of ``pkg/msg/Type`` from the ROS install (the rclpy-side resolver).

    Cached: a frame's outputs resolve a type name for each of about eight hundred messages,
    and the import-system lookup behind each (``importlib.import_module``) cost 0.8 ms of the
    12.8 ms the node's outputs took at 20 cars (median, A/B in one process). A message class
    never changes in a process."""
    package, _, type_name = name.split("/")
    return getattr(importlib.import_module(f"{package}.msg"), type_name)


#: rclpy's QoS overriding on every publisher and subscription of the nodes: the parameters
#: ``qos_overrides.<topic>.<publisher|subscription>.<history|depth|reliability>`` (read-only) set
#: the entity's policy over the node's own ``qos.*`` parameters.
QOS_OVERRIDES = QoSOverridingOptions.with_default_policies()
#: The values each overridable policy accepts (rclpy's policy names, lower case).
QOS_OVERRIDE_VALUES = {
    "history": ("keep_last", "keep_all", "system_default"),
    "reliability": ("reliable", "best_effort", "system_default", "best_available"),
}


@contextlib.contextmanager
def qos_override_errors():
    """rclpy's errors about a ``qos_overrides.*`` value as a :class:`ConfigError` naming it."""
    try:
        yield
    except (InvalidQosOverridesError, RuntimeError, InvalidParameterTypeException) as exc:
        raise ConfigError(f"qos_overrides: {exc}") from None


def check_qos_overrides(node: Node, core: NodeCore) -> None:
    """Refuse a ``qos_overrides.*`` parameter that names no topic of this node, or a policy or
    value rclpy does not override (rclpy would ignore the first silently: a typo must stop the
    node, as an unknown parameter does)."""
    topics = {node.resolve_topic_name(core.topics[name]): "subscription" for name in INPUTS}
    topics.update({node.resolve_topic_name(core.topics[name]): "publisher" for name in core.outputs})
    topics[node.resolve_topic_name(DIAGNOSTICS_TOPIC)] = "publisher"
    policies = ("history", "depth", "reliability")
    known = {f"qos_overrides.{topic}.{kind}.{policy}" for topic, kind in topics.items() for policy in policies}
    problems = []
    for name, parameter in node._parameter_overrides.items():
        if not name.startswith("qos_overrides."):
            continue
        if name not in known:
            problems.append(f"{name} (no such topic / entity / policy of this node; known: "
                            f"qos_overrides.<{' | '.join(sorted(topics))}>.<publisher|subscription>.<"
                            f"{' | '.join(policies)}>)")
            continue
        policy, value = name.rsplit(".", 1)[1], parameter.value
        if policy == "depth" and not (isinstance(value, int) and not isinstance(value, bool) and value >= 0):
            problems.append(f"{name}: depth must be a non-negative integer, not {value!r}")
        elif policy in QOS_OVERRIDE_VALUES and str(value).lower() not in QOS_OVERRIDE_VALUES[policy]:
            problems.append(f"{name}: {value!r} is not one of {', '.join(QOS_OVERRIDE_VALUES[policy])}")
    if problems:
        raise ConfigError("bad qos_overrides parameter(s): " + "; ".join(problems))


def qos_profile(qos: QoS) -> QoSProfile:
    """The rclpy profile of a seam :class:`QoS`."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=qos.depth,
        reliability=ReliabilityPolicy.RELIABLE if qos.reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if qos.transient_local else DurabilityPolicy.VOLATILE,
    )


class RclpyRuntime:
    """The :class:`~pcc_ros.runtime.base.Runtime` seam over one rclpy node."""

    classes = staticmethod(rclpy_classes)

    def __init__(self, node: Node) -> None:
        self.node = node
        self._tf_missing_logged = False
        self.tf = transform_source(node, self)  # tf2_ros, else the package's /tf listener

    @property
    def has_tf(self) -> bool:
        """True where transforms can be looked up (tf2_ros, or tf2_msgs for the package's listener)."""
        return self.tf is not None

    def create_publisher(self, topic, msgtype, qos):
        with qos_override_errors():
            return self.node.create_publisher(rclpy_classes(msgtype), topic, qos_profile(qos),
                                              qos_overriding_options=QOS_OVERRIDES)

    def create_subscription(self, topic, msgtype, callback, qos):
        with qos_override_errors():
            return self.node.create_subscription(rclpy_classes(msgtype), topic, callback, qos_profile(qos),
                                                 qos_overriding_options=QOS_OVERRIDES)

    def create_timer(self, period_s, callback):
        return self.node.create_timer(period_s, callback)

    def now_ns(self) -> int:
        return self.node.get_clock().now().nanoseconds

    def get_logger(self):
        return self.node.get_logger()

    def count_publishers(self, topic: str) -> int:
        return self.node.count_publishers(topic)

    def resolve_topic(self, topic: str) -> str:
        return self.node.resolve_topic_name(topic)

    def on_clock_jump(self, callback) -> None:
        """rcl's jump handler: called from the ``/clock`` callback that moved the clock back."""
        threshold = JumpThreshold(min_forward=None, min_backward=Duration(nanoseconds=-1_000_000),
                                  on_clock_change=True)
        self._jump_handler = self.node.get_clock().create_jump_callback(threshold, post_callback=lambda _: callback())

    def reset_transforms(self) -> None:
        if self.tf is not None:
            self.tf.clear()

    def lookup_transform(self, target: str, source: str, stamp_ns: int) -> Transform | None:
        if self.tf is None:
            if not self._tf_missing_logged:  # said once; the node core counts every skipped frame
                self._tf_missing_logged = True
                self.node.get_logger().warning(
                    f"neither tf2_ros nor tf2_msgs is installed: no transform '{source}' -> '{target}'; frames "
                    "that need one (detections in another frame than the scan, or an output_frame) are skipped "
                    "and counted (diagnostics: frames_without_transform). Run `make setup` (builds tf2_msgs "
                    "into the venv) or use a ROS 2 Jazzy install."
                )
            return None
        return self.tf.lookup(target, source, stamp_ns)


class RclpyLogHandler(logging.Handler):
    """The package's Python ``logging`` records (the message and pipeline layers: skipped
    detections, scores outside [0, 1], the crop work bound; a backend's load lines) on a node's
    rclpy logger, so they carry the node's name and ROS severity and reach ``/rosout`` like the
    node's own lines (without it they went to stderr as bare text, and not at all to ``/rosout``).

    One per process (:data:`LOG_HANDLER`), on the ``pcc_ros`` logger while a :class:`PipelineNode`
    lives. A record goes to one logger: the node's whose work logged it
    (:data:`pcc_ros.runtime.node.node_at_work`), so with two nodes in one process each line is said
    once, by its own node; a record of no node's work goes to the oldest node's logger. While it is
    attached, the package logger's level is the nodes' (rclpy's ``--log-level``, INFO by default)
    unless someone set one: a Python logger left at NOTSET passes only warnings and up (the root's
    level), so INFO lines never reached the handler."""

    def __init__(self) -> None:
        super().__init__()
        self.loggers: list = []  # the rclpy loggers of the live nodes, oldest first
        self._owns_level = False

    def attach(self, logger) -> None:
        package = logging.getLogger("pcc_ros")
        with self.lock:
            if not self.loggers:
                self._owns_level = package.level == logging.NOTSET
                package.addHandler(self)
            self.loggers.append(logger)
            self._follow_level(package)

    def detach(self, logger) -> None:
        package = logging.getLogger("pcc_ros")
        with self.lock:
            if logger not in self.loggers:
                return
            self.loggers.remove(logger)
            if self.loggers:
                self._follow_level(package)
                return
            package.removeHandler(self)
            if self._owns_level:
                package.setLevel(logging.NOTSET)

    def _follow_level(self, package: logging.Logger) -> None:
        """The package logger's level: the lowest of the live nodes' (INFO for an unset one),
        unless someone else set it before the first node attached."""
        if self._owns_level:
            package.setLevel(min(int(log.get_effective_level()) or logging.INFO for log in self.loggers))

    def emit(self, record: logging.LogRecord) -> None:
        try:
            logger = node_at_work.get()
            if logger is None and self.loggers:
                logger = self.loggers[0]
            elif logger not in self.loggers:  # an in-process (local runtime) node's work: its own logger says it
                return
            text = self.format(record)
            if record.levelno >= logging.ERROR:
                logger.error(text)
            elif record.levelno >= logging.WARNING:
                logger.warning(text)
            elif record.levelno >= logging.INFO:
                logger.info(text)
            else:
                logger.debug(text)
        except Exception:  # logging must never take a frame down
            self.handleError(record)


#: The process's one :class:`RclpyLogHandler`.
LOG_HANDLER = RclpyLogHandler()


def descriptor(spec: ParameterSpec) -> ParameterDescriptor:
    """The rclpy descriptor of a parameter: description, type, range, read-only flag."""
    out = ParameterDescriptor(
        description=spec.description,
        type=_TYPES[spec.type_name],
        read_only=spec.read_only,
        additional_constraints=spec.constraints,
    )
    if spec.range is not None and spec.type_name == "integer":
        out.integer_range = [IntegerRange(from_value=int(spec.range[0]), to_value=int(spec.range[1]), step=0)]
    elif spec.range is not None:
        out.floating_point_range = [
            FloatingPointRange(from_value=float(spec.range[0]), to_value=float(spec.range[1]), step=0.0)
        ]
    return out


def declare_parameters(node: Node) -> list[str]:
    """Declare every node parameter with its descriptor; returns the reasons of the values rclpy
    refused (wrong type, out of range: that parameter keeps its default), empty when none."""
    errors = []
    for spec in parameter_table():
        default = list(spec.default) if isinstance(spec.default, tuple) else spec.default
        try:
            node.declare_parameter(spec.name, default, descriptor(spec))
        except (InvalidParameterValueException, InvalidParameterTypeException) as exc:
            errors.append(f"parameter '{spec.name}': {exc}")
            node.declare_parameter(spec.name, default, descriptor(spec), ignore_override=True)
    return errors


def checked_values(node: Node) -> dict:
    """The node's parameter values; an unknown name among the given ones is a :class:`ConfigError`
    (rclpy ignores a parameter-file key nobody declares: a typo must stop the node instead)."""
    unknown = unknown_parameters(node._parameter_overrides)
    if unknown:
        raise ConfigError(f"unknown node parameter(s): {unknown} (see docs/nodes.md for the list)")
    return {spec.name: node.get_parameter(spec.name).value for spec in parameter_table()}


class PipelineNode(Node):
    """Completion (``mode="completion"``) or detection filtering (``mode="filter"``)."""

    def __init__(self, node_name: str, mode: str, **node_options) -> None:
        """``node_options`` go to ``rclpy.node.Node`` (e.g. ``parameter_overrides`` in tests)."""
        super().__init__(node_name, **node_options)
        self.mode = mode
        LOG_HANDLER.attach(self.get_logger())
        try:
            self._start(node_name, mode)
        except BaseException:
            self.destroy_node()  # a node that never ran takes its log handler (and rcl node) with it
            raise

    def _start(self, node_name: str, mode: str) -> None:
        """Declare and check the parameters, then build the node core and serve."""
        errors = declare_parameters(self)
        if errors:
            raise ConfigError(errors[0])
        self.core = NodeCore(RclpyRuntime(self), node_name, mode, checked_values(self), connect=False)
        check_qos_overrides(self, self.core)
        self.core.connect()
        self.add_on_set_parameters_callback(self._on_set_parameters)  # after declaring: run-time changes only

    def _on_set_parameters(self, parameters) -> SetParametersResult:
        """``ros2 param set``: the node core validates and swaps (or refuses, with the reason)."""
        result = self.core.set_parameters({p.name: p.value for p in parameters})
        return SetParametersResult(successful=result.successful, reason=result.reason)

    def destroy_node(self) -> None:
        LOG_HANDLER.detach(self.get_logger())
        if hasattr(self, "core"):
            self.core.shutdown()
        super().destroy_node()


def startup_error(exc: BaseException, argv: list[str]) -> str:
    """One line for an ``rclpy.init`` failure: a ``--params-file`` that does not read names its
    file and line as ``pcc replay`` does; anything else is rcl's text without its C source places."""
    files = [value for flag, value in itertools.pairwise(argv) if flag == "--params-file"]
    for path in files:
        try:
            read_parameters(path)
        except ConfigError as problem:
            return str(problem)
    return re.sub(r",? at /\S+", "", str(exc)).strip() + " — check the --ros-args"


def run(node_name: str, mode: str, args: list[str] | None = None, node_class: type = PipelineNode) -> int:
    """``main()`` of both nodes: init, spin, clean shutdown on Ctrl-C / external shutdown.
    ``node_class``: :class:`PipelineNode`, or the managed (lifecycle) host."""
    try:
        # rcl's own parser first: rclpy.init on a bad --ros-args line or parameter file also logs
        # "[rcl]: Failed to parse global arguments" before raising, a second, vaguer line above ours
        remove_ros_args(args=args)
        rclpy.init(args=args)
    except RuntimeError as exc:  # rclpy's RCLError (not exported): a bad --ros-args line or parameter file
        rclpy.logging.get_logger(node_name).fatal(startup_error(exc, sys.argv if args is None else list(args)))
        return 1
    node = None
    try:
        node = node_class(node_name, mode)
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
