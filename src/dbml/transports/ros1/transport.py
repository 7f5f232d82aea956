"""The ROS 1 transport: real ROS topics, the ROS parameter server and the master's graph.

- Topics: ``[topic]`` and ``[topic]/optimized`` are ordinary ROS topics of the message class
  registered for the topic (``use_message_class``). A payload is the serialised message: it is
  sent as it is (no second serialisation) and received raw, so its length is the serialised
  size. Topics without a class (dbml's own JSON reports) travel as ``std_msgs/String``.
- Parameters: the real parameter server, under the paper's absolute names, so ``rosparam get``
  and ``rosparam set`` work on them; mirrored here from the master's pushes
  (``dbml.transports.ros1.params``).
- Graph: the master's ``getSystemState``, by the host of each node
  (``dbml.transports.ros1.graph``).
- No attachments: ROS 1 messages carry none, so subscribers see ``attachment=None`` (no
  per-message latency or loss, hence no bandwidth estimation over ROS 1).

rospy allows one node per process, so there is one ``Ros1Transport`` per process
(``Ros1Transport.shared()`` opens it on first use); it reuses a node the application already
started with ``rospy.init_node``.
"""

from __future__ import annotations

import atexit
import importlib
import io
import logging
import struct
import sys
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any
from urllib.parse import urlparse

from dbml.core.errors import TransportError
from dbml.transports.base import (
    Closer,
    Handle,
    Sample,
    TransportBase,
    TransportPriority,
    Variant,
    check_topic,
    resolve_host,
)
from dbml.transports.codecs import ROS1_FLOAT64
from dbml.transports.replica import Replica
from dbml.transports.ros1.graph import GRAPH_POLL_S, Ros1Graph, split
from dbml.transports.ros1.master import ROSPY_MISSING, MasterClient
from dbml.transports.ros1.params import Ros1Params
from dbml.transports.worker import FLUSH_TIMEOUT_S

try:
    import rosgraph.network
    import rospy
    import std_msgs.msg
except ImportError as err:  # pragma: no cover - depends on the machine
    raise ImportError(ROSPY_MISSING) from err

__all__ = ["Ros1Transport", "serialize"]

log = logging.getLogger("dbml.ros1")

RECEIVE_BUFFER_BYTES = 1 << 24
"""rospy's receive buffer per subscription: room for a few large camera frames."""
_STRING = std_msgs.msg.String
_FRAME_PREFIX_BYTES = 4
"""A ``std_msgs/String`` starts with its length (uint32)."""


class _SlotTakenError(TransportError):
    """Another ``Ros1Transport`` is open (or opening) in this process."""


class _Slot:
    """The process's one transport (rospy runs one node per process).

    A transport reserves the slot under the lock, starts outside it (XML-RPC to the master and
    ``init_node`` are slow) and fills it, or releases it if it fails; ``shared()`` waits for a
    transport being opened instead of opening a second.
    """

    def __init__(self) -> None:
        self.changed = threading.Condition()
        self.opening = False
        self.transport: Ros1Transport | None = None

    def reserve(self) -> None:
        with self.changed:
            if self.opening or self.transport is not None:
                raise _SlotTakenError("one Ros1Transport per process (rospy runs one node)")
            self.opening = True

    def settle(self, transport: Ros1Transport | None) -> None:
        """End a reservation: ``transport`` opened, or None when opening failed."""
        with self.changed:
            self.opening = False
            self.transport = transport
            self.changed.notify_all()

    def release(self, transport: Ros1Transport) -> None:
        with self.changed:
            if self.transport is transport:
                self.transport = None
            self.changed.notify_all()


_SLOT = _Slot()


def serialize(message: Any) -> bytes:
    """A rospy message as it goes on the wire (without the 4-byte length prefix)."""
    buffer = io.BytesIO()
    message.serialize(buffer)
    return buffer.getvalue()


def _use_host(host: str) -> None:
    """Make this process's ROS node take ``host`` as its address, before the node starts.

    rosgraph reads the override on every use (the node's URI, each topic connection's address,
    the bind address), from ``__hostname:=`` on the command line first, then ``ROS_HOSTNAME`` /
    ``ROS_IP``. There is no per-node setting, so it goes where it stays inside this process: the
    command line's ROS remapping (first, so it wins), not the environment, which every child
    process would inherit.
    """
    sys.argv.insert(1, f"__hostname:={resolve_host(host)}")


def _raw_class(data_class: type) -> type:
    """A message class of ``data_class``'s ROS type whose instances hold serialised bytes."""

    class Raw(rospy.AnyMsg):  # type: ignore[misc]
        _type = data_class._type  # type: ignore[attr-defined]
        _md5sum = data_class._md5sum  # type: ignore[attr-defined]
        _full_text = data_class._full_text  # type: ignore[attr-defined]
        __slots__ = ()

        def __init__(self, buff: bytes) -> None:
            self._buff = buff  # type: ignore[misc]  # AnyMsg's slot

    return Raw


class _Received(rospy.AnyMsg):  # type: ignore[misc]
    """Raw incoming bytes; rospy attaches the connection header (it needs a ``__dict__``)."""


class _Ros1Publisher:
    """A ROS publisher sending payloads as they are (already serialised)."""

    def __init__(self, topic: str, variant: Variant, data_class: type | None, queue: int) -> None:
        self.topic = topic
        self._framed = data_class is None
        self._raw = _raw_class(_STRING if data_class is None else data_class)
        self._publisher = rospy.Publisher(variant.key(topic), self._raw, queue_size=queue)

    def put(self, payload: bytes, *, attachment: bytes | None = None) -> None:
        if self._framed:
            payload = struct.pack("<I", len(payload)) + payload
        self._publisher.publish(self._raw(payload))

    @property
    def has_subscribers(self) -> bool:
        return bool(self._publisher.get_num_connections() > 0)

    def close(self) -> None:
        self._publisher.unregister()


class Ros1Transport(TransportBase):
    """dbml over a ROS 1 master; one per process (``shared()`` opens it on first use).

    ``node_name`` is used only when no node runs in this process yet. ``host`` is the address
    the node gives others (its URI's host, as ``ROS_HOSTNAME`` / ``ROS_IP`` would set it); it
    can only be chosen before the node starts.
    """

    float64 = ROS1_FLOAT64
    """ROS 1's serialisation of a ``std_msgs/Float64`` (a priority from a topic)."""

    def __init__(
        self,
        *,
        host: str | None = None,
        node_name: str = "dbml",
        anonymous: bool = True,
        message_classes: Mapping[str, type] | None = None,
        queue_size: int = 10,
        graph_poll_s: float = GRAPH_POLL_S,
    ) -> None:
        self._classes: dict[str, type] = dict(message_classes or {})
        self._declared_types: dict[str, str] = {}
        """Topics typed by ``set_topic_type``: raw bytes of a type whose class may be missing."""
        self._learned: dict[str, type] = {}
        """Type, md5 and definition of such a topic, as its publisher's connection header said."""
        self._queue_size = queue_size
        self._handles: set[Handle] = set()
        self._closed = False
        _SLOT.reserve()
        try:
            self._start(host=host, node_name=node_name, anonymous=anonymous, poll_s=graph_poll_s)
        except BaseException:
            _SLOT.settle(None)
            raise
        _SLOT.settle(self)

    def _start(self, *, host: str | None, node_name: str, anonymous: bool, poll_s: float) -> None:
        with MasterClient() as master:
            if not master.reachable():
                raise TransportError(
                    f"no ROS master at ROS_MASTER_URI={master.uri} (start one: rosmaster --core)"
                )
        if rospy.core.is_shutdown_requested() or rospy.is_shutdown():
            raise TransportError("this process's rospy node has shut down; start a new one")
        self._owns_node = not rospy.core.is_initialized()
        if self._owns_node:
            if host is not None:
                _use_host(host)
            rospy.init_node(node_name, anonymous=anonymous, disable_signals=True)
        self.node_name = str(rospy.get_name())
        uri_host = urlparse(rospy.get_node_uri()).hostname
        self._host = str(uri_host or rosgraph.network.get_host_name())
        if host is not None and host != self._host:
            if self._owns_node:  # ours, and of no use: do not leave it running without an owner
                rospy.signal_shutdown("dbml transport failed to start")
            raise TransportError(
                f"host={host!r} cannot apply: this process's ROS node already runs on "
                f"{self._host!r} (set ROS_HOSTNAME or ROS_IP before it starts)"
            )
        self._master = MasterClient(master.uri, caller_id=self.node_name)
        self._params = Ros1Params(
            self._master, self.node_name, self._host, rosgraph.network.get_bind_address()
        )
        self._graph = Ros1Graph(self._master, poll_s)
        # A node that exits without closing (a rospy user's) still sends its queued writes.
        atexit.register(self._flush_at_exit)

    def _flush_at_exit(self) -> None:
        if not self._closed and not self._params.replica.flush(FLUSH_TIMEOUT_S):
            log.warning("exiting with parameter writes unsent after %.1f s", FLUSH_TIMEOUT_S)

    @classmethod
    def shared(cls) -> Ros1Transport:
        """This process's transport, opened on first use (on the rospy node, if one runs).

        A transport being opened by another thread is waited for, never opened twice.
        """
        while True:
            with _SLOT.changed:
                while _SLOT.opening:
                    _SLOT.changed.wait()
                if _SLOT.transport is not None:
                    return _SLOT.transport
            try:
                return cls()
            except _SlotTakenError:
                continue  # another thread reserved the slot first: wait for its transport

    @classmethod
    def current(cls) -> Ros1Transport | None:
        """This process's open transport, if any."""
        with _SLOT.changed:
            return _SLOT.transport

    @property
    def host(self) -> str:
        """The host part of this node's URI: what other nodes connect to."""
        return self._host

    @property
    def params(self) -> Replica:
        """The parameter server, mirrored here."""
        return self._params.replica

    def confirm_param(self, name: str, *, timeout_s: float) -> bool:
        """Whether the master holds what this process holds of ``name``, once it is sent.

        ``set`` only queues the write: a process that writes and exits must wait for it.
        """
        return self._params.confirm(name, timeout_s=timeout_s)

    @property
    def graph(self) -> Ros1Graph:
        """The master's registrations, by host."""
        return self._graph

    def use_message_class(self, topic: str, data_class: type) -> None:
        """Carry ``topic`` (both copies) as ``data_class``, e.g. ``sensor_msgs.msg.Image``."""
        check_topic(topic)
        if not hasattr(data_class, "_md5sum") or not hasattr(data_class, "_type"):
            raise TransportError(f"data_class={data_class!r} is not a rospy message class")
        self._classes[topic] = data_class

    def declare_publisher(
        self,
        topic: str,
        variant: Variant = Variant.FULL,
        *,
        priority: TransportPriority | None = None,
        express: bool = False,
    ) -> _Ros1Publisher:
        """A ROS publisher of the topic's message class (``std_msgs/String`` without one).

        ROS 1 has one TCP connection per topic and no classes: ``priority`` and ``express`` are
        ignored.
        """
        self._check_open()
        check_topic(topic)
        data_class = self._classes.get(topic) or self._learned.get(topic)
        if data_class is None and topic in self._declared_types:
            raise TransportError(
                f"topic={topic!r}: type {self._declared_types[topic]!r} has no Python class "
                "here; subscribe to the topic first (its header tells the md5)"
            )
        return _Ros1Publisher(topic, variant, data_class, self._queue_size)

    def subscribe(
        self, topic: str, callback: Callable[[Sample], None], variant: Variant = Variant.FULL
    ) -> Handle:
        """A ROS subscriber that hands ``callback`` the serialised message as it arrived."""
        self._check_open()
        check_topic(topic)
        typed = topic in self._classes or topic in self._declared_types

        def deliver(message: _Received) -> None:
            payload: bytes = message._buff
            if typed and topic not in self._learned:
                self._learn(topic, message._connection_header)
            if not typed and message._connection_header.get("type") == _STRING._type:
                payload = payload[_FRAME_PREFIX_BYTES:]  # a framed untyped payload
            callback(Sample(topic, payload, None))

        subscriber = rospy.Subscriber(
            variant.key(topic),
            _Received,
            deliver,
            buff_size=RECEIVE_BUFFER_BYTES,
            tcp_nodelay=True,
        )

        def unsubscribe() -> None:
            subscriber.unregister()
            self._handles.discard(handle)  # a closed subscription is not kept until exit

        handle = Closer(unsubscribe)
        self._handles.add(handle)
        return handle

    def _learn(self, topic: str, header: Mapping[str, str]) -> None:
        """Keep a typed topic's type, md5 and definition, to republish its bytes as they are."""
        header_class = type(
            "Header",
            (),
            {
                "_type": header.get("type", ""),
                "_md5sum": header.get("md5sum", "*"),
                "_full_text": header.get("message_definition", ""),
            },
        )
        self._learned[topic] = _raw_class(header_class)

    def topic_type(self, topic: str, *, timeout_s: float) -> str | None:
        """The master's type of ``topic`` (``getTopicTypes``), waiting up to ``timeout_s``."""
        check_topic(topic)
        deadline = time.monotonic() + timeout_s
        while True:
            for name, msg_type in self._master.call("getTopicTypes"):
                if name == topic and msg_type != "*":
                    return str(msg_type)
            if time.monotonic() >= deadline:
                return None
            time.sleep(min(GRAPH_POLL_S, max(0.0, deadline - time.monotonic())))

    def set_topic_type(self, topic: str, msg_type: str) -> None:
        """Carry ``topic`` (both copies) as raw bytes of ``msg_type`` (``pkg/Name``).

        Its Python class is used when installed (``pkg.msg.Name``); else the md5 and definition
        come from the connection header of the first message received on ``topic``.
        """
        base, _variant = split(check_topic(topic))
        package, _, name = msg_type.rpartition("/")
        package = package.removesuffix("/msg")  # ROS 2 spelling: pkg/msg/Name
        if not package or "/" in package or not name:
            raise TransportError(f"type={msg_type!r} must look like 'sensor_msgs/Image'")
        declared = self._declared_types.setdefault(base, f"{package}/{name}")
        if declared != f"{package}/{name}":
            raise TransportError(f"topic={topic!r} has type {declared!r}, not {msg_type!r}")
        try:
            data_class = getattr(importlib.import_module(f"{package}.msg"), name, None)
        except ImportError:
            data_class = None
        if data_class is not None and hasattr(data_class, "_md5sum"):
            self.use_message_class(base, data_class)

    def now(self) -> float:
        """Monotonic seconds."""
        return time.monotonic()

    def _check_open(self) -> None:
        if self._closed:
            raise TransportError("transport is closed")

    def close(self) -> None:
        """Unregister everything; shut the node down if this transport started it."""
        if self._closed:
            return
        self._closed = True
        atexit.unregister(self._flush_at_exit)
        for handle in list(self._handles):
            handle.close()
        self._graph.close()
        self._params.close()
        if self._owns_node:
            rospy.signal_shutdown("dbml transport closed")
        _SLOT.release(self)
