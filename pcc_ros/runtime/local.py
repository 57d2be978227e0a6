"""An in-process ROS-like graph: node logic without any middleware.

Several :class:`LocalRuntime` (one per node) share a :class:`LocalGraph`. ``publish``
delivers the message object itself, synchronously and in the publisher's thread, to every
subscription on the same topic whose QoS matches (a best-effort writer never reaches a
reliable reader, as in DDS). Messages are rosbags dataclasses (``classes`` =
:func:`pcc_ros.msg.typestore.rosbags_classes`), the flavour bags use.

The clock is the wall clock, or — with ``LocalGraph(simulated=True)`` — a simulated one
that only moves through :meth:`LocalGraph.advance_to` (``use_sim_time`` for offline work:
timers fire when simulated time passes their deadline, so diagnostics of a replayed
bag are reproducible). Transforms come from the graph's
:class:`~pcc_ros.msg.tf_buffer.TransformBuffer` (:meth:`LocalGraph.set_transform`, or a
bag's ``/tf`` and ``/tf_static`` loaded by ``pcc replay``), looked up through the tree as tf2 does.

Uses: the node-core tests (a real runtime, no mock of ROS), benchmarks that separate node
cost from transport cost, and embedding nodes in one process.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from pcc_ros.msg.tf_buffer import TransformBuffer
from pcc_ros.msg.typestore import rosbags_classes
from pcc_ros.runtime.base import QoS, Transform


def resolve_topic(topic: str, namespace: str = "/") -> str:
    """ROS name resolution for the names the nodes use: relative names go under ``namespace``."""
    if topic.startswith("/"):
        return topic
    ns = namespace.rstrip("/")
    return f"{ns}/{topic}"


@dataclass
class _Subscription:
    msgtype: str
    callback: Callable[[Any], None]
    qos: QoS
    received: int = 0
    topic_name: str = ""


@dataclass
class _Timer:
    period_ns: int
    callback: Callable[[], None]
    next_ns: int


@dataclass
class LocalGraph:
    """Topics shared by the runtimes of one process."""

    simulated: bool = False
    _subs: dict[str, list[_Subscription]] = field(default_factory=lambda: defaultdict(list))
    _types: dict[str, str] = field(default_factory=dict)
    _publishers: dict[str, int] = field(default_factory=lambda: defaultdict(int))
    _jump_callbacks: list[Callable[[], None]] = field(default_factory=list)
    _timers: list[_Timer] = field(default_factory=list)
    transforms: TransformBuffer = field(default_factory=TransformBuffer)
    _sim_ns: int = 0
    _lock: threading.RLock = field(default_factory=threading.RLock)

    def now_ns(self) -> int:
        return self._sim_ns if self.simulated else time.time_ns()

    def advance_to(self, stamp_ns: int) -> None:
        """Move the simulated clock forward and fire every timer that came due, in time order."""
        if not self.simulated:
            raise RuntimeError("advance_to needs LocalGraph(simulated=True)")
        while True:
            with self._lock:
                due = [t for t in self._timers if t.next_ns <= stamp_ns]
                if not due:
                    self._sim_ns = max(self._sim_ns, int(stamp_ns))
                    return
                timer = min(due, key=lambda t: t.next_ns)
                self._sim_ns = max(self._sim_ns, timer.next_ns)
                timer.next_ns += timer.period_ns
            timer.callback()

    def jump_to(self, stamp_ns: int) -> None:
        """Move the simulated clock to ``stamp_ns``, backwards too (a looped bag or a reset simulator
        under ``use_sim_time``); every timer's next deadline restarts from there, as rcl's do."""
        if not self.simulated:
            raise RuntimeError("jump_to needs LocalGraph(simulated=True)")
        with self._lock:
            back = int(stamp_ns) < self._sim_ns
            self._sim_ns = int(stamp_ns)
            for timer in self._timers:
                timer.next_ns = self._sim_ns + timer.period_ns
            callbacks = list(self._jump_callbacks) if back else []
        for callback in callbacks:
            callback()

    def set_transform(self, target: str, source: str, transform: Transform) -> None:
        """Static transform ``source`` -> ``target``, i.e. the edge ``target <- source`` (what
        ``/tf_static`` would carry with ``target`` as the parent frame)."""
        self.transforms.set_transform(target, source, transform)

    def _check_type(self, topic: str, msgtype: str) -> None:
        known = self._types.setdefault(topic, msgtype)
        if known != msgtype:
            raise TypeError(f"topic {topic} carries {known}, not {msgtype}")

    def subscribers(self, topic: str) -> int:
        return len(self._subs.get(topic, ()))

    def publishers(self, topic: str) -> int:
        """Publishers created on ``topic`` (they live as long as the graph)."""
        return self._publishers.get(topic, 0)


class _LocalPublisher:
    def __init__(self, graph: LocalGraph, topic: str, qos: QoS) -> None:
        self.graph, self.topic, self.qos = graph, topic, qos
        self.published = 0

    def get_subscription_count(self) -> int:
        """Subscriptions on this topic whose QoS this publisher can serve (as DDS matching)."""
        with self.graph._lock:
            return sum(self.qos.compatible_with_reader(sub.qos) for sub in self.graph._subs.get(self.topic, ()))

    def publish(self, msg: Any) -> None:
        self.published += 1
        with self.graph._lock:
            subs = list(self.graph._subs.get(self.topic, ()))
        for sub in subs:
            if self.qos.compatible_with_reader(sub.qos):
                sub.received += 1
                sub.callback(msg)


class LocalRuntime:
    """One node's runtime on a :class:`LocalGraph` (see the module docstring)."""

    classes = staticmethod(rosbags_classes)

    def __init__(self, graph: LocalGraph, node_name: str, namespace: str = "/") -> None:
        self.graph, self.node_name, self.namespace = graph, node_name, namespace
        self._logger = logging.getLogger(f"pcc_ros.{node_name}")
        self._threads: list[threading.Thread] = []
        self._stop = threading.Event()

    def create_publisher(self, topic: str, msgtype: str, qos: QoS) -> _LocalPublisher:
        name = resolve_topic(topic, self.namespace)
        self.graph._check_type(name, msgtype)
        with self.graph._lock:
            self.graph._publishers[name] += 1
        return _LocalPublisher(self.graph, name, qos)

    def create_subscription(self, topic: str, msgtype: str, callback: Callable[[Any], None], qos: QoS) -> _Subscription:
        name = resolve_topic(topic, self.namespace)
        self.graph._check_type(name, msgtype)
        sub = _Subscription(msgtype, callback, qos, topic_name=name)
        with self.graph._lock:
            self.graph._subs[name].append(sub)
        return sub

    def create_timer(self, period_s: float, callback: Callable[[], None]) -> Any:
        """Simulated graph: fires from :meth:`LocalGraph.advance_to`. Wall clock: a daemon thread."""
        period_ns = int(period_s * 1e9)
        if self.graph.simulated:
            timer = _Timer(period_ns, callback, self.graph.now_ns() + period_ns)
            with self.graph._lock:
                self.graph._timers.append(timer)
            return timer

        def loop() -> None:
            while not self._stop.wait(period_s):
                callback()

        thread = threading.Thread(target=loop, name=f"{self.node_name}_timer", daemon=True)
        thread.start()
        self._threads.append(thread)
        return thread

    def now_ns(self) -> int:
        return self.graph.now_ns()

    def get_logger(self) -> logging.Logger:
        return self._logger

    def lookup_transform(self, target: str, source: str, stamp_ns: int) -> Transform | None:
        return self.graph.transforms.lookup(target, source, stamp_ns)

    def on_clock_jump(self, callback: Callable[[], None]) -> None:
        with self.graph._lock:
            self.graph._jump_callbacks.append(callback)

    def reset_transforms(self) -> None:
        self.graph.transforms.clear_dynamic()

    def count_publishers(self, topic: str) -> int:
        return self.graph.publishers(topic)

    def resolve_topic(self, topic: str) -> str:
        return resolve_topic(topic, self.namespace)

    def shutdown(self) -> None:
        """Stop wall-clock timers (subscriptions stay registered: the graph outlives nodes in tests)."""
        self._stop.set()
        for thread in self._threads:
            thread.join(timeout=2.0)
