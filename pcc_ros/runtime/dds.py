"""A ROS 2 wire-compatible runtime over Cyclone DDS (the ``cyclonedds`` PyPI package), no ROS install.

Wire conventions (as rmw_cyclonedds in Jazzy; checked against a real rclpy):

* ROS topic ``/points`` is DDS topic ``rt/points``; relative names resolve under the
  namespace (``/`` by default);
* types are :mod:`pcc_ros.runtime.idl` classes named ``pkg::msg::dds_::Type_``, final
  extensibility, XCDR1 (the DataRepresentation QoS pins XCDR1 on every endpoint);
* every reader and writer carries USER_DATA ``typehash=RIHS01_<hex>;`` (the RIHS01 hash
  of the rosbags type store), the participant ``enclave=/;``;
* QoS is always explicit (:class:`~pcc_ros.runtime.base.QoS` -> reliability, keep-last
  depth, durability);
* discovery follows ``ROS_DOMAIN_ID`` / ``ROS_AUTOMATIC_DISCOVERY_RANGE``
  (:mod:`pcc_ros.runtime.discovery`).

Threading: one spin thread waits on a WaitSet over all readers, takes samples one at a
time, converts them to rosbags messages and calls the callbacks. A sample that cannot be
decoded is logged, counted (:attr:`DdsRuntime.undecodable`) and skipped; an exception in
a callback is logged and the spin thread keeps serving.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any

from cyclonedds.core import GuardCondition, InstanceState, Policy, Qos, ReadCondition, SampleState, ViewState, WaitSet
from cyclonedds.domain import Domain, DomainParticipant
from cyclonedds.pub import DataWriter, Publisher
from cyclonedds.sub import DataReader, Subscriber
from cyclonedds.topic import Topic
from cyclonedds.util import duration

from pcc_ros.errors import MessageError
from pcc_ros.msg.typestore import rosbags_classes, type_hash
from pcc_ros.runtime import idl
from pcc_ros.runtime.base import QoS, Transform
from pcc_ros.runtime.discovery import Discovery
from pcc_ros.runtime.local import resolve_topic

log = logging.getLogger(__name__)


def dds_topic_name(topic: str, namespace: str = "/") -> str:
    """ROS topic name -> DDS topic name (``/points`` -> ``rt/points``)."""
    return "rt" + resolve_topic(topic, namespace)


def endpoint_qos(qos: QoS, msgtype: str) -> Qos:
    """DDS QoS of a reader or writer: explicit reliability/history/durability, XCDR1, USER_DATA typehash."""
    return Qos(
        Policy.Reliability.Reliable(duration(milliseconds=100)) if qos.reliable else Policy.Reliability.BestEffort,
        Policy.History.KeepLast(qos.depth),
        Policy.Durability.TransientLocal if qos.transient_local else Policy.Durability.Volatile,
        Policy.DataRepresentation(use_cdrv0_representation=True, use_xcdrv2_representation=False),
        Policy.Userdata(f"typehash={type_hash(msgtype)};".encode()),
    )


class DdsPublisher:
    """Publishes rosbags (or attribute-compatible) messages of one type on one topic."""

    def __init__(self, runtime: DdsRuntime, topic: str, msgtype: str, qos: QoS) -> None:
        self.msgtype = msgtype
        self.topic_name = dds_topic_name(topic, runtime.namespace)
        topic_entity = runtime._topic(self.topic_name, msgtype)
        self.writer = DataWriter(runtime.publisher, topic_entity, endpoint_qos(qos, msgtype))
        self.published = 0

    def publish(self, msg: Any) -> None:
        self.writer.write(idl.to_idl(self.msgtype, msg))
        self.published += 1

    def matched(self) -> int:
        """Readers currently matched (discovery done, QoS compatible)."""
        return len(self.writer.get_matched_subscriptions())


class DdsSubscription:
    def __init__(self, runtime: DdsRuntime, topic: str, msgtype: str, callback: Callable[[Any], None], qos: QoS):
        self.msgtype, self.callback = msgtype, callback
        self.topic_name = dds_topic_name(topic, runtime.namespace)
        topic_entity = runtime._topic(self.topic_name, msgtype)
        self.reader = DataReader(runtime.subscriber, topic_entity, endpoint_qos(qos, msgtype))
        self.condition = ReadCondition(self.reader, SampleState.NotRead | ViewState.Any | InstanceState.Any)
        self.received = 0

    def matched(self) -> int:
        """Writers currently matched."""
        return len(self.reader.get_matched_publications())


class DdsRuntime:
    """The :class:`~pcc_ros.runtime.base.Runtime` seam over Cyclone DDS, for one node (one participant).

    Call :meth:`start` once the subscriptions exist (or use it as a context manager) and
    :meth:`shutdown` at the end. Transforms: none (no tf listener yet), so detections must
    arrive in the scan's frame.
    """

    classes = staticmethod(rosbags_classes)

    def __init__(self, node_name: str, namespace: str = "/", discovery: Discovery | None = None) -> None:
        self.node_name, self.namespace = node_name, namespace
        self.discovery = discovery or Discovery.from_env()
        self._domain = _domain(self.discovery)
        self.participant = DomainParticipant(self.discovery.domain_id, qos=Qos(Policy.Userdata(b"enclave=/;")))
        self.publisher = Publisher(self.participant)
        self.subscriber = Subscriber(self.participant)
        self._topics: dict[str, Topic] = {}
        self._subs: list[DdsSubscription] = []
        self._waitset = WaitSet(self.participant)
        self._wake = GuardCondition(self.participant)
        self._waitset.attach(self._wake)
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._logger = logging.getLogger(f"pcc_ros.{node_name}")
        self.undecodable = 0
        self.callback_errors = 0

    # ---------------------------------------------------------------- seam

    def _topic(self, name: str, msgtype: str) -> Topic:
        topic = self._topics.get(name)
        if topic is None:
            topic = self._topics[name] = Topic(self.participant, name, idl.idl_class(msgtype))
        elif topic.data_type is not idl.idl_class(msgtype):
            raise MessageError(f"topic {name} already has type {topic.data_type.__idl_typename__}")
        return topic

    def create_publisher(self, topic: str, msgtype: str, qos: QoS) -> DdsPublisher:
        return DdsPublisher(self, topic, msgtype, qos)

    def create_subscription(
        self, topic: str, msgtype: str, callback: Callable[[Any], None], qos: QoS
    ) -> DdsSubscription:
        sub = DdsSubscription(self, topic, msgtype, callback, qos)
        self._subs.append(sub)
        self._waitset.attach(sub.condition)
        self._wake.set(True)  # let a running spin loop pick the new reader up
        return sub

    def create_timer(self, period_s: float, callback: Callable[[], None]) -> threading.Thread:
        def loop() -> None:
            while not self._stop.wait(period_s):
                try:
                    callback()
                except Exception as exc:
                    self._logger.error(f"timer callback failed: {type(exc).__name__}: {exc}")

        thread = threading.Thread(target=loop, name=f"{self.node_name}_timer", daemon=True)
        thread.start()
        self._threads.append(thread)
        return thread

    def now_ns(self) -> int:
        return time.time_ns()

    def get_logger(self) -> logging.Logger:
        return self._logger

    def lookup_transform(self, target: str, source: str, stamp_ns: int) -> Transform | None:
        self._logger.warning("the DDS runtime has no tf listener; publish detections in the scan's frame")
        return None

    # ---------------------------------------------------------------- spinning

    def start(self) -> DdsRuntime:
        """Start the spin thread (idempotent)."""
        if not any(t.name.endswith("_spin") for t in self._threads):
            thread = threading.Thread(target=self._spin, name=f"{self.node_name}_spin", daemon=True)
            thread.start()
            self._threads.append(thread)
        return self

    def spin_once(self, timeout_s: float = 0.1) -> int:
        """Wait up to ``timeout_s`` for data, dispatch everything available; returns samples dispatched."""
        self._waitset.wait(duration(seconds=timeout_s))
        self._wake.set(False)
        done = 0
        for sub in list(self._subs):
            done += self._drain(sub)
        return done

    def _spin(self) -> None:
        while not self._stop.is_set():
            self.spin_once(0.2)

    def _drain(self, sub: DdsSubscription) -> int:
        done = 0
        while not self._stop.is_set():
            try:
                samples = sub.reader.take(N=1)
            except Exception as exc:  # the sample is gone from the reader: count it and go on
                self.undecodable += 1
                self._logger.warning(f"undecodable sample on {sub.topic_name} skipped: {type(exc).__name__}: {exc}")
                continue
            if not samples:
                return done
            sample = samples[0]
            if not getattr(getattr(sample, "sample_info", None), "valid_data", True):
                continue
            try:
                msg = idl.from_idl(sub.msgtype, sample)
            except Exception as exc:
                self.undecodable += 1
                self._logger.warning(f"undecodable sample on {sub.topic_name} skipped: {type(exc).__name__}: {exc}")
                continue
            sub.received += 1
            done += 1
            try:
                sub.callback(msg)
            except Exception as exc:  # a callback bug must not stop the node
                self.callback_errors += 1
                self._logger.error(f"callback on {sub.topic_name} failed: {type(exc).__name__}: {exc}")
        return done

    def shutdown(self) -> None:
        """Stop threads and delete the participant (and with it every reader and writer)."""
        self._stop.set()
        self._wake.set(True)
        for thread in self._threads:
            thread.join(timeout=2.0)
        self._threads.clear()

    def __enter__(self) -> DdsRuntime:
        return self

    def __exit__(self, *exc) -> None:
        self.shutdown()


_DOMAINS: dict[int, tuple[Discovery, Domain | None]] = {}
_DOMAINS_LOCK = threading.Lock()


def _domain(discovery: Discovery) -> Domain | None:
    """The process's configured Domain for ``discovery.domain_id`` (created once; Cyclone allows one).

    The Domain object carries the configuration and must outlive every participant in it.
    """
    with _DOMAINS_LOCK:
        known = _DOMAINS.get(discovery.domain_id)
        if known is not None:
            if known[0] != discovery:
                raise MessageError(f"DDS domain {discovery.domain_id} is already configured otherwise in this process")
            return known[1]
        xml = discovery.cyclone_xml()
        domain = Domain(discovery.domain_id, xml) if xml else None
        _DOMAINS[discovery.domain_id] = (discovery, domain)
        return domain


def wait_for(predicate: Callable[[], bool], timeout_s: float, step_s: float = 0.05) -> bool:
    """Poll ``predicate`` until true or ``timeout_s`` passes (discovery waits)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(step_s)
    return predicate()
