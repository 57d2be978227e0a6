"""The managed (lifecycle) host of both nodes: ``completion_node_managed``, ``detection_filter_node_managed``.

ROS 2's node lifecycle (``rclpy.lifecycle``; driven through ``/<node>/change_state`` and read
through ``/<node>/get_state``, e.g. by ``ros2 lifecycle set`` or a launch file's lifecycle
manager), over the same :class:`~pcc_ros.runtime.node.NodeCore` as the plain node:

* ``configure``: the parameters are checked (an unknown name, a wrong type, a value out of range,
  a bad ``qos_overrides.*`` or a backend that does not load fails the transition, its reason
  logged) and the pipeline is loaded: backend, weights, compiled kernels. Nothing is published
  or subscribed yet.
* ``activate``: the lifecycle publishers, the subscriptions, the diagnostics timer and the
  worker are created; frames are answered.
* ``deactivate``: they are destroyed and the worker stops; the pipeline stays loaded, so a
  later ``activate`` serves at once.
* ``cleanup`` / ``shutdown`` (and ``on_error``): the pipeline is dropped and its memory
  collected.
"""

from __future__ import annotations

from rcl_interfaces.msg import SetParametersResult
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn

from pcc_ros.errors import PccError
from pcc_ros.nodes.ros_node import (
    LOG_HANDLER,
    QOS_OVERRIDES,
    RclpyRuntime,
    check_qos_overrides,
    checked_values,
    declare_parameters,
    qos_override_errors,
    qos_profile,
    rclpy_classes,
)
from pcc_ros.pipeline.config import node_parameters
from pcc_ros.runtime.heap import freeze_long_lived
from pcc_ros.runtime.node import NodeCore


class LifecycleRuntime(RclpyRuntime):
    """The rclpy runtime of a managed node: lifecycle publishers (silent unless active), and every
    entity it creates remembered, so ``deactivate`` destroys what ``activate`` made."""

    def __init__(self, node: LifecycleNode) -> None:
        #: what the runtime's own parts made while it was built (the /tf listener's subscriptions):
        #: they live from configure to cleanup
        self.lasting: list = []
        self.entities: list = self.lasting
        super().__init__(node)
        #: what the node core made when it started serving: activate to deactivate
        self.entities = []

    def create_publisher(self, topic, msgtype, qos):
        with qos_override_errors():
            publisher = self.node.create_lifecycle_publisher(
                rclpy_classes(msgtype), topic, qos_profile(qos), qos_overriding_options=QOS_OVERRIDES
            )
        self.entities.append(publisher)
        return publisher

    def create_subscription(self, topic, msgtype, callback, qos):
        subscription = super().create_subscription(topic, msgtype, callback, qos)
        self.entities.append(subscription)
        return subscription

    def create_timer(self, period_s, callback):
        timer = super().create_timer(period_s, callback)
        self.entities.append(timer)
        return timer

    def destroy_entities(self, lasting: bool = False) -> None:
        """Destroy every publisher, subscription and timer the node core made since the last call
        (``lasting``: and the runtime's own, at cleanup)."""
        node = self.node
        for entity in reversed([*self.entities, *(self.lasting if lasting else [])]):
            if entity in node._managed_entities:
                node.destroy_lifecycle_publisher(entity)
            elif hasattr(entity, "timer_period_ns"):
                node.destroy_timer(entity)
            elif hasattr(entity, "publish"):
                node.destroy_publisher(entity)
            else:
                node.destroy_subscription(entity)
        self.entities = []
        if lasting:
            self.lasting = []


class ManagedPipelineNode(LifecycleNode):
    """Completion (``mode="completion"``) or detection filtering (``mode="filter"``) as a managed node."""

    def __init__(self, node_name: str, mode: str, **node_options) -> None:
        """``node_options`` go to ``rclpy.lifecycle.LifecycleNode`` (e.g. ``parameter_overrides``)."""
        super().__init__(node_name, **node_options)
        self.mode = mode
        self.core: NodeCore | None = None
        self.runtime: LifecycleRuntime | None = None
        LOG_HANDLER.attach(self.get_logger())
        #: values rclpy refused at declaration (their defaults stand in): ``configure`` fails with them
        self._declare_errors = declare_parameters(self)
        self.add_on_set_parameters_callback(self._on_set_parameters)

    # ------------------------------------------------------------- transitions

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        try:
            if self._declare_errors:
                raise PccError(self._declare_errors[0])
            self.runtime = LifecycleRuntime(self)
            core = NodeCore(self.runtime, self.get_name(), self.mode, checked_values(self), connect=False)
            check_qos_overrides(self, core)
        except Exception as exc:  # a bad parameter (PccError), or anything else: said, and the node stays unconfigured
            reason = str(exc) if isinstance(exc, PccError) else f"{type(exc).__name__}: {exc}"
            self.get_logger().error(f"configure failed: {reason}")
            if self.runtime is not None:
                self.runtime.destroy_entities(lasting=True)
            self.runtime = None
            return TransitionCallbackReturn.FAILURE
        self.core = core
        self.get_logger().info("configured: pipeline loaded; activate to serve")
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        try:
            self.core.connect()
        except PccError as exc:
            self.get_logger().error(f"activate failed: {exc}")
            self._stop_serving()
            return TransitionCallbackReturn.FAILURE
        return super().on_activate(state)  # enables the lifecycle publishers

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        result = super().on_deactivate(state)  # publishers silent from here on
        self._stop_serving()
        self.get_logger().info("deactivated: not serving; the pipeline stays loaded")
        return result

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._unload()
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._stop_serving()
        self._unload()
        return TransitionCallbackReturn.SUCCESS

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._stop_serving()
        self._unload()
        return TransitionCallbackReturn.SUCCESS  # back to unconfigured: configure may be tried again

    def _stop_serving(self) -> None:
        if self.core is not None:
            self.core.shutdown()
        if self.runtime is not None:
            self.runtime.destroy_entities()

    def _unload(self) -> None:
        """Drop the node core and its pipeline; the collection frees the backend's memory now."""
        self.core = None
        if self.runtime is not None:
            self.runtime.destroy_entities(lasting=True)
        self.runtime = None
        freeze_long_lived()  # unfreezes, collects (the dropped backend with it), freezes what is left

    # ------------------------------------------------------------- parameters

    def _on_set_parameters(self, parameters) -> SetParametersResult:
        """Configured: the node core validates and swaps, as in the plain node. Unconfigured: the
        values are only checked (``configure`` reads them)."""
        changes = {p.name: p.value for p in parameters if not p.name.startswith("qos_overrides.")}
        if self.core is not None:
            result = self.core.set_parameters(changes)
            return SetParametersResult(successful=result.successful, reason=result.reason)
        try:
            node_parameters(None, {k: v for k, v in changes.items() if k != "use_sim_time"})
        except PccError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    def destroy_node(self) -> None:
        LOG_HANDLER.detach(self.get_logger())
        self._stop_serving()
        self.core = None
        super().destroy_node()
