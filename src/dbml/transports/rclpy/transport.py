"""The rclpy transport: real ROS 2 through the user's own rclpy, on whatever RMW it runs.

Tested with Fast DDS (Kilted's ``ros-*`` wheels, ``pip install 'dbml[rclpy]'``); a sourced
``/opt/ros/<distro>`` works the same. In the runtime, only this package imports rclpy (the
harness and the plain ROS 2 peers of the experiment use it too, as plain ROS 2 nodes).

- **Data** is raw CDR both ways: a publisher sends the bytes it is given (``publish(bytes)``), a
  subscription hands over what arrived (``raw=True``); nothing is re-serialised. A topic's type
  comes from ``set_topic_type`` (``--type``) or the graph; topics of dbml's own untyped bytes
  travel as ``std_msgs/msg/UInt8MultiArray`` whose ``data`` is the payload. A subscription
  waits for its topic's type before it exists, and matches its publishers' reliability (a
  best-effort driver is heard best effort). dbml's per-message metadata is DDS's own: a
  sample's writer sequence number and source timestamp (where the RMW fills them, as Fast DDS
  does) are its ``seq`` and send time, so estimation works; the rate in force does not travel.
- **Parameters** are real ROS 2 parameters on ``/dbm`` and ``[topic]/dbm``
  (``dbml.transports.rclpy.params``).
- **Graph**: the DDS graph itself, read every ``GRAPH_POLL_S`` (ROS 1's rule: ``announce``
  declares nothing, the real endpoints are the graph), by host (``dbml.transports.rclpy.graph``).
- **A full link never stalls or kills a publisher**: a publish that the middleware refuses
  (asynchronous Fast DDS raises after its queue stays full) is dropped and counted; a
  synchronous publish waits at most one frame's send.
- **Hygiene**: each transport has its own context (``SignalHandlerOptions.NO``: signals stay
  the program's), its own domain if given, one executor thread that reports its death, and
  leaves nothing behind when closed.
"""

from __future__ import annotations

import collections
import importlib
import logging
import math
import re
import struct
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from dbml.core.errors import TransportError
from dbml.core.extras import require
from dbml.protocol import keys
from dbml.protocol.metadata import pack_meta
from dbml.protocol.names import check_topic
from dbml.protocol.schema import GLOBAL_PREFIX, Writer, lookup
from dbml.transports.base import (
    COMPRESSED_TYPE,
    GraphEntry,
    Handle,
    Sample,
    TransportBase,
    TransportPriority,
    Variant,
    resolve_host,
)
from dbml.transports.overflow import LogOnce, Overflow
from dbml.transports.rclpy.fastdds import GID_BYTES
from dbml.transports.rclpy.graph import MAX_TOPICS, Graph, node_name_for, read_graph
from dbml.transports.rclpy.nodes import (
    check_ros_topic,
    is_param_node,
    python_value,
)
from dbml.transports.rclpy.params import RclpyParams
from dbml.transports.rclpy.rosargs import overrides, qos_overrides
from dbml.transports.replica import Replica
from dbml.transports.worker import FLUSH_TIMEOUT_S, BackgroundThread

RCLPY_HINT = "or source your ROS 2: . /opt/ros/<distro>/setup.bash"
"""The other way to rclpy: a ROS 2 install (robots are often aarch64, where no wheels exist)."""

require("rclpy", extra="rclpy", what="transport 'rclpy'", hint=RCLPY_HINT)

import rclpy  # noqa: E402  (after require: its error names the extra)
from rclpy.context import Context  # noqa: E402
from rclpy.event_handler import (  # noqa: E402
    PublisherEventCallbacks,
    UnsupportedEventTypeError,
)
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter as RosParameter  # noqa: E402
from rclpy.qos import (  # noqa: E402
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_parameter_events,
)
from rclpy.qos_overriding_options import QoSOverridingOptions  # noqa: E402
from rclpy.signals import SignalHandlerOptions  # noqa: E402

__all__ = [
    "ALLOCATION_QOS",
    "BYTES_TYPE",
    "GRAPH_POLL_S",
    "PUBLISH_TIMES",
    "RCLPY_HINT",
    "PublishStats",
    "RclpyTransport",
    "frame_bytes",
    "message_class",
    "sample_meta",
    "unframe_bytes",
]

log = logging.getLogger("dbml.rclpy")

BYTES_TYPE = "std_msgs/msg/UInt8MultiArray"
"""The type of a topic of dbml's own untyped bytes (its ``data`` is the payload)."""
GRAPH_POLL_S = 0.1
"""How often the DDS graph is read (a local cache: tens of microseconds per topic)."""
SPIN_TIMEOUT_S = 0.1
"""The executor thread's longest wait, so closing is noticed."""
PUBLISH_DEPTH = 5
"""Messages a publisher keeps for a late or slow reliable reader (KEEP_LAST: never blocks)."""
SUBSCRIPTION_DEPTH = 10
"""Messages a subscription queues for its callback (KEEP_LAST: the oldest go first)."""
PUBLISH_TIMES = 4_096
"""Durations of ``publish()`` a publisher keeps for its p99: the newest (its max covers all)."""
MAX_SOON = 65_536
"""Work items waiting for the executor thread at most (each a write batch or a release)."""
ALLOCATION_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=1,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)
"""The newest whole allocation, kept for a host that matches the ``/dbm`` node late."""
_BYTES_HEADER = struct.Struct("<4sIII")
"""CDR of an ``UInt8MultiArray`` with no dimensions: encapsulation, dims, offset, data length."""
_CDR_LE = b"\x00\x01\x00\x00"
_ROS_PACKAGE = re.compile(r"^[a-z][a-z0-9_]*$")


def frame_bytes(payload: bytes) -> bytes:
    """``payload`` as the CDR of an ``UInt8MultiArray`` (``BYTES_TYPE``)."""
    return _BYTES_HEADER.pack(_CDR_LE, 0, 0, len(payload)) + payload


def unframe_bytes(data: bytes) -> bytes | None:
    """The payload of a serialised ``UInt8MultiArray`` with no dimensions; None otherwise."""
    if len(data) < _BYTES_HEADER.size:
        return None
    header, dims, _offset, size = _BYTES_HEADER.unpack_from(data)
    if header != _CDR_LE or dims != 0 or len(data) - _BYTES_HEADER.size < size:
        return None
    return data[_BYTES_HEADER.size : _BYTES_HEADER.size + size]


def sample_meta(info: Any) -> bytes | None:
    """Dbml's metadata of a received message from DDS's own sample info, if the RMW fills it.

    The writer's sequence number (gaps are losses) and its wall-clock source timestamp (the
    send time) are what estimation needs; the publisher's rate does not travel (NaN).
    """
    if not isinstance(info, dict):
        return None
    seq, sent_ns = info.get("publication_sequence_number"), info.get("source_timestamp")
    if not isinstance(seq, int) or not isinstance(sent_ns, int) or seq <= 0 or sent_ns <= 0:
        return None
    return pack_meta(seq, sent_ns, math.nan)


def _sender(info: Any) -> bytes | None:
    """The publisher GID in a message's info (16 bytes), if the RMW gives it."""
    gid = info.get("publisher_gid") if isinstance(info, dict) else None
    data = gid.get("data") if isinstance(gid, dict) else None
    return bytes(data)[:GID_BYTES] if isinstance(data, bytes | bytearray | list) else None


def message_class(msg_type: str) -> type:
    """The Python class of ``pkg/msg/Name``; ``TransportError`` saying what to install."""
    package, kind, name = [*msg_type.split("/"), "", "", ""][:3]
    if kind != "msg" or not _ROS_PACKAGE.match(package) or not name.isidentifier():
        raise TransportError(f"type={msg_type!r} must look like 'pkg/msg/Name'")
    try:
        module = importlib.import_module(f"{package}.msg")
    except ImportError:
        raise TransportError(
            f"type={msg_type!r}: Python package {package!r} is missing: "
            f"pip install ros-{package.replace('_', '-')} (or source the ROS 2 that has it)"
        ) from None
    cls = getattr(module, name, None)
    if not isinstance(cls, type) or not hasattr(cls, "get_fields_and_field_types"):
        raise TransportError(f"type={msg_type!r}: {package}.msg has no message {name!r}")
    return cls


def _void(_result: object) -> None:
    """Drop a result (rclpy's ``destroy_*`` return a bool nobody needs)."""


def _guarded(what: str, callback: Callable[..., None]) -> Callable[..., None]:
    """``callback`` for the executor thread: an exception in it is logged, never its death."""

    def run(*args: Any) -> None:
        try:
            callback(*args)
        except Exception:
            log.exception("%s failed", what)

    return run


@dataclass(frozen=True, slots=True)
class PublishStats:
    """How long a publisher's ``publish()`` calls took, logged when it closes.

    A synchronous Fast DDS publish waits for the socket on a full link; this says how long.
    """

    topic: str
    """The ROS topic (``[topic]/optimized`` for a managed copy)."""
    published: int
    """Calls that returned (the message went to the middleware)."""
    dropped: int
    """Calls the middleware refused (raised, counted, never passed on)."""
    max_ms: float | None
    """The longest call of all, refused ones included."""
    p99_ms: float | None
    """The 99th percentile of the newest ``PUBLISH_TIMES`` calls."""


class _RclpyPublisher:
    """A publisher of raw CDR; what the middleware refuses is dropped and counted.

    Each ``put`` is timed (two clock reads and an append to a bounded deque): ``stats()``, and
    one INFO line at ``close`` carrying them as ``extra={"publish_stats": ...}``.
    """

    def __init__(self, transport: RclpyTransport, topic: str, variant: Variant) -> None:
        self.topic = topic
        self._transport = transport
        self._type = transport.resolve_type(topic, variant) or BYTES_TYPE
        self._framed = self._type == BYTES_TYPE
        self._matched: int | None = None
        """Subscriptions matched, as the middleware's matched events last said (None where the
        RMW has no such event: then asked on every call)."""
        qos = QoSProfile(
            history=HistoryPolicy.KEEP_LAST,
            depth=PUBLISH_DEPTH,
            reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.VOLATILE,
        )
        # The managed copy's QoS may be overridden as any ROS 2 publisher's
        # (``qos_overrides.<topic>.publisher.reliability`` and so on, from the params file).
        overriding = QoSOverridingOptions.with_default_policies() if variant.managed else None
        try:
            self._publisher: Any = transport.node.create_publisher(
                message_class(self._type),
                variant.key(topic),
                qos,
                event_callbacks=PublisherEventCallbacks(matched=self._on_matched),
                qos_overriding_options=overriding,
            )
            count = self._publisher.get_subscription_count()
            if self._matched is None:  # a matched event since is newer than this count
                self._matched = count
        except UnsupportedEventTypeError:
            self._publisher = transport.node.create_publisher(
                message_class(self._type),
                variant.key(topic),
                qos,
                qos_overriding_options=overriding,
            )
        self.dropped = 0
        """Messages the middleware refused (a link full for longer than its queue)."""
        self.published = 0
        self._ros_topic = variant.key(topic)
        self._refusing = 0
        """While the middleware refuses: ``dropped`` at the first refusal (told once per run)."""
        self._durations: collections.deque[float] = collections.deque(maxlen=PUBLISH_TIMES)
        self._max_s = 0.0

    def put(self, payload: bytes, *, attachment: bytes | None = None) -> None:
        """Send ``payload``; never raises on a full link (the refusal is counted)."""
        start = time.perf_counter()
        try:
            self._publisher.publish(frame_bytes(payload) if self._framed else payload)
        except Exception as err:  # rclpy's RCLError: the queue stayed full, or a shutdown
            self.dropped += 1
            if not self._refusing:
                self._refusing = self.dropped
                log.warning(
                    "%s: the middleware refuses messages (%s): dropping them", self._ros_topic, err
                )
        else:
            self.published += 1
            if self._refusing:
                log.warning(
                    "%s: publishing again; %d dropped meanwhile",
                    self._ros_topic,
                    self.dropped - self._refusing + 1,
                )
                self._refusing = 0
        took = time.perf_counter() - start
        self._durations.append(took)
        self._max_s = max(self._max_s, took)

    def stats(self) -> PublishStats:
        """How long ``put``'s publish calls took so far."""
        durations = sorted(self._durations)
        p99 = durations[min(len(durations) - 1, int(0.99 * len(durations)))] if durations else None
        return PublishStats(
            self._ros_topic,
            self.published,
            self.dropped,
            self._max_s * 1e3 if durations else None,
            None if p99 is None else p99 * 1e3,
        )

    def _on_matched(self, status: Any) -> None:
        """A subscription matched or left (executor thread): the count ``has_subscribers`` reads.

        Read on every publish, the count would cost a middleware call each time.
        """
        self._matched = int(status.current_count)

    @property
    def has_subscribers(self) -> bool:
        """Whether any subscription matches (from matched events, where the RMW has them)."""
        if self._matched is None:
            return bool(self._publisher.get_subscription_count() > 0)
        return self._matched > 0

    def close(self) -> None:
        stats = self.stats()
        if stats.max_ms is not None:
            log.info(
                "%s: %d published, publish() max %.2f ms, p99 %.2f ms, %d dropped",
                stats.topic,
                stats.published,
                stats.max_ms,
                stats.p99_ms,
                stats.dropped,
                extra={"publish_stats": stats},
            )
        publisher = self._publisher
        self._transport.release(lambda: _void(self._transport.node.destroy_publisher(publisher)))


class _Subscription:
    """One ``subscribe`` call: a raw subscription created once the topic's type is known."""

    def __init__(
        self,
        transport: RclpyTransport,
        topic: str,
        variant: Variant,
        callback: Callable[[Sample], None],
    ) -> None:
        self.topic = topic
        self.variant = variant
        self.ros_topic = variant.key(topic)
        self._transport = transport
        self._callback = callback
        self.closed = False
        self.subscription: Any = None
        self.reliable: bool | None = None
        self.msg_type: str | None = None

    def deliver(self, data: bytes, info: Any) -> None:
        """One message, with what DDS says of it as dbml's metadata (``sample_meta``)."""
        if self.closed:
            return
        try:
            if self._framed:
                payload = unframe_bytes(data)
                if payload is None:
                    return
                data = payload
            self._callback(Sample(self.topic, data, sample_meta(info)))
        except Exception:  # the executor thread must outlive any callback
            log.exception("a subscription callback of %s failed", self.ros_topic)

    def ensure(self, msg_type: str, *, reliable: bool) -> None:
        """Create the subscription, or re-create it for its publishers' type and reliability."""
        if self.closed or (
            self.subscription is not None
            and self.reliable == reliable
            and self.msg_type == msg_type
        ):
            return
        node = self._transport.node
        if self.subscription is not None:
            node.destroy_subscription(self.subscription)
        self._framed = msg_type == BYTES_TYPE
        self.reliable = reliable
        self.msg_type = msg_type
        self.subscription = node.create_subscription(
            message_class(msg_type),
            self.ros_topic,
            self.deliver,
            QoSProfile(
                history=HistoryPolicy.KEEP_LAST,
                depth=SUBSCRIPTION_DEPTH,
                reliability=ReliabilityPolicy.RELIABLE
                if reliable
                else ReliabilityPolicy.BEST_EFFORT,
            ),
            raw=True,
        )

    _framed = False

    def close(self) -> None:
        self.closed = True
        self._transport.forget(self)


class RclpyTransport(TransportBase):
    """dbml over rclpy: one private context, one node (``dbml_<host>__<id>``), one executor.

    ``domain_id`` (else ``ROS_DOMAIN_ID``) picks the ROS 2 domain of this transport's context.
    """

    def __init__(
        self,
        host: str | None = None,
        *,
        domain_id: int | None = None,
        ros_args: Sequence[str] = (),
    ) -> None:
        self._host = resolve_host(host)
        self.ros_args = tuple(ros_args)
        self.ros_values = overrides(self.ros_args)  # checked before anything starts
        """dbml's parameters given in ``ros_args`` (a params file, ``-p``), by full name."""
        qos_overrides(self.ros_args)  # checked too, before anything starts
        self.context = Context()
        options: dict[str, Any] = {"signal_handler_options": SignalHandlerOptions.NO}
        if domain_id is not None:
            options["domain_id"] = domain_id
        if self.ros_args:
            options["args"] = ["dbml", *self.ros_args]
        try:
            rclpy.init(context=self.context, **options)
        except _rclpy.UnknownROSArgsError as err:
            raise TransportError(f"--ros-args: rclpy does not know {err}") from None
        except _rclpy.RCLError as err:
            raise TransportError(f"--ros-args: {err}") from None
        self._lock = threading.Lock()
        self._closed = False
        self._soon: collections.deque[Callable[[], None]] = collections.deque()
        self._soon_overflow = Overflow("tasks for the executor", MAX_SOON, log=log)
        self._subscriptions: list[_Subscription] = []
        self._declared_types: dict[str, str] = {}
        self._graph_types: dict[str, str] = {}
        self._best_effort: set[str] = set()
        """ROS topics with at least one best-effort publisher."""
        self._dbml_peers = 0
        self._bad = LogOnce(log)
        self._poll_queued = False
        self._topics_overflow = Overflow("graph topics", MAX_TOPICS, log=log)
        self._graph = Graph()
        self._polled = threading.Event()
        try:
            # Its name says dbml's host to every peer: no remapping moves it.
            self.node = Node(
                node_name_for(self._host),
                context=self.context,
                use_global_arguments=False,
                parameter_overrides=[
                    RosParameter(name, value=value)
                    for name, value in qos_overrides(self.ros_args).items()
                ],
            )
            self._executor = SingleThreadedExecutor(context=self.context)
            self._executor.add_node(self.node)
            self._wake = self.node.create_guard_condition(self._run_soon)
            self._sync = RclpyParams(self)
            self.node.create_subscription(
                _parameter_event(),
                "/parameter_events",
                self._on_parameter_event,
                qos_profile_parameter_events,
            )
            self.node.create_subscription(
                _string(),
                keys.ALLOCATION_TOPIC,
                self._on_allocation,
                ALLOCATION_QOS,
            )
            self.node.create_timer(GRAPH_POLL_S, _guarded("the graph poll", self._poll))
        except Exception:
            rclpy.try_shutdown(context=self.context)
            raise
        self._thread = BackgroundThread(self._spin, name="dbml-rclpy", log=log).start()
        for name, value in self.ros_values.items():  # as ``dbml budget`` would write them
            found = lookup(name)
            if found is not None and Writer.OPERATOR in found[0].writers:
                self.params.set(name, value)

    # -- the executor thread -------------------------------------------------------------------

    def _spin(self) -> None:
        """Spin until closed; a callback's exception is logged, never the thread's death.

        rclpy re-raises it out of ``spin_once``, its own parameter services' too, which any
        node's request feeds.
        """
        while not self._closed and self.context.ok():
            try:
                self._executor.spin_once(timeout_sec=SPIN_TIMEOUT_S)
            except Exception as err:  # input from the network must not end the executor
                if self._closed or not self.context.ok():
                    return
                self._bad.warning(
                    f"spin:{type(err).__name__}", "a callback failed (ignored): %r", err
                )

    def call_soon(self, task: Callable[[], None]) -> None:
        """Run ``task`` on the executor thread (where every rclpy call of dbml's runs)."""
        self._queue(task)

    def _queue(self, task: Callable[[], None]) -> bool:
        """Queue ``task`` for the executor thread; False if closed or the queue is full."""
        with self._lock:
            if self._closed:
                return False
            if len(self._soon) >= MAX_SOON:
                self._soon_overflow.refuse()
                return False
            self._soon.append(task)
        self._wake.trigger()
        return True

    def run(self, task: Callable[[], None]) -> bool:
        """Run ``task`` on the executor thread and wait until it ran (the parameter sender's).

        False, without waiting longer, once the transport closes or its executor thread dies.
        """
        if self._thread.is_current():
            task()
            return True
        done = threading.Event()

        def step() -> None:
            try:
                task()
            finally:
                done.set()

        while not self._queue(step):  # the queue is full: it drains
            if self._closed or not self._thread.alive or done.wait(SPIN_TIMEOUT_S):
                return False
        while not done.wait(SPIN_TIMEOUT_S):
            if self._closed or not self._thread.alive:
                return False
        return True

    def _run_soon(self) -> None:
        while True:
            with self._lock:
                if not self._soon:
                    return
                task = self._soon.popleft()
            try:
                task()
            except Exception:
                log.exception("an executor task failed")

    def poll_soon(self) -> None:
        """Read the graph at once rather than at the next tick (once, however often asked)."""
        if not self._poll_queued:
            self._poll_queued = True
            self.call_soon(self._poll)

    def release(self, action: Callable[[], None]) -> None:
        """Destroy an entity on the executor thread (never under a wait)."""
        self.call_soon(action)

    def add_node(self, node: Node) -> None:
        """Spin a parameter node with the transport's own (executor thread)."""
        self._executor.add_node(node)

    def remove_node(self, node: Node) -> None:
        """Stop spinning and destroy a parameter node (executor thread)."""
        self._executor.remove_node(node)
        node.destroy_node()

    def string_publisher(self, node: Node, topic: str) -> Any:
        """``node``'s ``std_msgs/msg/String`` publisher of the newest whole allocation."""
        return node.create_publisher(_string(), topic, ALLOCATION_QOS)

    def _on_parameter_event(self, event: Any, info: Any) -> None:
        """A parameter node's changes, with their sender (two arguments: the message info).

        Anyone may publish on ``/parameter_events`` naming any node: ``RclpyParams.on_event``
        believes an event only from a participant that hosts the node it names.
        """
        try:
            node = event.node
            namespace, _, name = node.rpartition("/")
            fqn = is_param_node(namespace or "/", name)
            if fqn is None:
                return
            # A parameter declared with no value says nothing (a new host declares every one);
            # one changed to no value, or undeclared, is deleted. A value of a type dbml cannot
            # hold is refused by the store, named.
            changed = [(p.name, python_value(p.value)) for p in event.new_parameters]
            changed = [(name, value) for name, value in changed if value is not None]
            changed += [(p.name, python_value(p.value)) for p in event.changed_parameters]
            changed += [(p.name, None) for p in event.deleted_parameters]
            self._sync.on_event(fqn, changed, sender=_sender(info))
        except Exception:
            log.exception("a parameter event could not be handled")

    def _on_allocation(self, message: Any, info: Any) -> None:
        """``/dbm/allocation`` with its sender (two arguments: rclpy passes the message info)."""
        try:
            self._sync.on_allocation(message.data, sender=_sender(info))
        except Exception:
            log.exception("an allocation could not be handled")

    def _poll(self) -> None:
        """Read the graph; type and re-create the waiting subscriptions; tell the store."""
        self._poll_queued = False
        read = read_graph(self.node, topics_overflow=self._topics_overflow, bad=self._bad)
        with self._lock:
            self._graph_types = read.types
            self._best_effort = read.best_effort
            self._dbml_peers = read.dbml_peers
            waiting = [s for s in self._subscriptions if not s.closed]
        for subscription in waiting:
            msg_type = (
                COMPRESSED_TYPE
                if subscription.variant is Variant.COMPRESSED
                else self._declared_types.get(subscription.topic)
                or read.types.get(subscription.ros_topic)
            )
            if msg_type is None:
                continue
            try:
                subscription.ensure(
                    msg_type, reliable=subscription.ros_topic not in read.best_effort
                )
            except Exception as err:  # a type or name from the network: that one only
                self._bad.warning(subscription.ros_topic, "cannot subscribe: %s", err)
        self._sync.poll(read.param_hosts, read.claimed, read.own, read.senders)
        self._graph.update(read.entries)
        self._polled.set()

    # -- the Transport protocol ----------------------------------------------------------------

    @property
    def host(self) -> str:
        """This process's host identity (in its node's name)."""
        return self._host

    @property
    def params(self) -> Replica:
        """The parameters of every ``/dbm`` and ``[topic]/dbm`` node, as last heard."""
        return self._sync.replica

    @property
    def graph(self) -> Graph:
        """The DDS graph's endpoints by host."""
        return self._graph

    def resolve_type(self, topic: str, variant: Variant = Variant.FULL) -> str | None:
        """The type declared for ``topic`` or, else, the one its graph shows.

        A camera's compressed copy is always ``sensor_msgs/msg/CompressedImage``.
        """
        if variant is Variant.COMPRESSED:
            return COMPRESSED_TYPE
        with self._lock:
            return (
                self._declared_types.get(topic)
                or self._graph_types.get(variant.key(topic))
                or self._graph_types.get(topic)
            )

    def declare_publisher(
        self,
        topic: str,
        variant: Variant = Variant.FULL,
        *,
        priority: TransportPriority | None = None,
        express: bool = False,
    ) -> _RclpyPublisher:
        """A publisher of raw CDR of the topic's type (dbml's bytes type if it has none)."""
        check_ros_topic(topic)
        self._check_open()
        return _RclpyPublisher(self, topic, variant)

    def subscribe(
        self, topic: str, callback: Callable[[Sample], None], variant: Variant = Variant.FULL
    ) -> Handle:
        """Hear ``topic`` raw, once its type is known (declared, or from its publishers)."""
        check_ros_topic(topic)
        self._check_open()
        subscription = _Subscription(self, topic, variant, callback)
        with self._lock:
            self._subscriptions.append(subscription)
        self.call_soon(self._poll)
        return subscription

    def forget(self, subscription: _Subscription) -> None:
        """A closed subscription: destroyed on the executor thread."""
        with self._lock:
            if subscription in self._subscriptions:
                self._subscriptions.remove(subscription)

        def destroy() -> None:
            if subscription.subscription is not None:
                self.node.destroy_subscription(subscription.subscription)
                subscription.subscription = None

        self.call_soon(destroy)

    now = staticmethod(time.monotonic)
    """Monotonic seconds: the clock itself, no Python frame of dbml's (read on every publish)."""

    def wait_for_peers(self, timeout_s: float) -> bool:
        """Wait until another dbml node is seen and every parameter node met was read."""
        deadline = time.monotonic() + timeout_s
        while True:
            with self._lock:
                peers = self._dbml_peers > 0
            if peers and self._sync.settled():
                return True
            if time.monotonic() >= deadline:
                return False
            self._polled.clear()
            self._polled.wait(min(GRAPH_POLL_S * 2, max(0.0, deadline - time.monotonic())))

    def refresh(self, entry: GraphEntry) -> None:
        """Read the parameters of ``entry``'s channel again from its node."""
        self._sync.refresh(f"{entry.topic}{GLOBAL_PREFIX}")

    def confirm_param(self, name: str, *, timeout_s: float) -> bool:
        """Whether another process's node took this process's latest write of ``name``."""
        deadline = time.monotonic() + timeout_s
        while not self._sync.confirmed(name):
            if time.monotonic() >= deadline:
                return False
            self._polled.clear()
            self._polled.wait(GRAPH_POLL_S)
        return True

    def topic_type(self, topic: str, *, timeout_s: float) -> str | None:
        """The type the graph shows for ``topic``'s publishers, waiting up to ``timeout_s``."""
        check_topic(topic)
        deadline = time.monotonic() + timeout_s
        while True:
            with self._lock:
                found = self._graph_types.get(topic)
            if found is not None or time.monotonic() >= deadline:
                return found
            self._polled.clear()
            self._polled.wait(GRAPH_POLL_S * 2)

    def set_topic_type(self, topic: str, msg_type: str) -> None:
        """Declare ``topic``'s type (its Python class must be importable: else what to install)."""
        check_ros_topic(topic)
        message_class(msg_type)
        with self._lock:
            declared = self._declared_types.setdefault(topic, msg_type)
        if declared != msg_type:
            raise TransportError(f"topic={topic!r} has type {declared!r}, not {msg_type!r}")
        self.call_soon(self._poll)

    def _check_open(self) -> None:
        if self._closed:
            raise TransportError("the rclpy transport is closed")

    @property
    def alive(self) -> bool:
        """False once the executor thread or the parameter sender died."""
        return self._thread.alive and self._sync.replica.alive

    def close(self) -> None:
        """Send what is queued, stop the executor thread, destroy every node, shut down.

        Writes still queued for the executor go first (bounded by ``FLUSH_TIMEOUT_S``), as the
        zenoh store flushes its own: a process that writes and exits loses nothing it could
        send.
        """
        with self._lock:
            if self._closed:
                return
        waits = self._thread.alive and not self._thread.is_current()
        # The parameter writes first: their sender hands each to the executor and waits for it.
        if not self._sync.replica.close(FLUSH_TIMEOUT_S if waits else 0.0):
            log.warning("closing with parameter writes unsent (the executor was busy)")
        flushed = threading.Event()
        self.call_soon(flushed.set)
        if waits and not flushed.wait(FLUSH_TIMEOUT_S):
            log.warning("closing with writes still queued (the executor was busy)")
        with self._lock:
            self._closed = True
        self._wake.trigger()
        self._thread.join()
        if self._thread.running:
            log.warning("the executor thread did not stop: its nodes are left to the exit")
            return
        try:
            self._sync.close()
            self._executor.shutdown(timeout_sec=1.0)
            self.node.destroy_node()
        finally:
            rclpy.try_shutdown(context=self.context)


def _parameter_event() -> type:
    from rcl_interfaces.msg import ParameterEvent

    cls: type = ParameterEvent
    return cls


def _string() -> type:
    from std_msgs.msg import String

    cls: type = String
    return cls
