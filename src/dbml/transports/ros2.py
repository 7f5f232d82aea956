"""The ros2 transport: rmw_zenoh's wire format on a zenoh session, beside dbml's own keys.

A managed ``[topic]/optimized`` is an ordinary ROS 2 topic: its messages travel under rmw_zenoh's
typed keys with its 33-byte attachment, and dbml's node, publishers and subscriptions declare
rmw_zenoh's liveliness tokens, so ``ros2 topic list``/``info`` show them with their types.
dbml's parameter store and graph (``dbml/**``) run unchanged in the same zenoh session
(``dbml.transports.zenoh``), so dbml processes over ``ros2`` and over ``zenoh`` still meet.

ROS 2 nodes take part without knowing dbml: a ROS 2 subscription of ``X/optimized`` appears in
the graph as a subscriber of channel ``X`` (so the optimizer manages it), a ROS 2 publisher's
token tells ``topic_type`` its type, and a ``std_msgs/msg/Float64`` on ``X/dbm/priority`` sets
the channel's priority. Everything read from the network is validated; a malformed token or
value is logged once and ignored.

Topology as rmw_zenoh's: peer mode, connect to the router of this host (``tcp/localhost:7447``,
``dbml router`` or ``rmw_zenohd``), listen on a port of its own, no multicast, no shared memory.
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
import threading
import time
import uuid
from collections.abc import Callable, Sequence
from pathlib import Path

import zenoh

from dbml.core.errors import TransportError
from dbml.transports.base import (
    Closer,
    GraphEntry,
    GraphView,
    Handle,
    ParamStore,
    Role,
    Sample,
    TransportBase,
    Variant,
    check_topic,
)
from dbml.transports.callbacks import CallbackList
from dbml.transports.ros2msg import (
    ADMIN_SPACE,
    FLOAT64_TYPE,
    IMAGE_TYPE,
    QOS_RELIABLE_VOLATILE_KEEP_LAST_10,
    Attachment,
    LivelinessToken,
    MessageTypes,
    TokenKind,
    check_domain_id,
    data_key,
    decode_float64,
    encode_attachment,
    image_cdr,
    parse_token,
)
from dbml.transports.zenoh import ZenohTransport, open_router

__all__ = [
    "DEFAULT_LISTEN",
    "DEFAULT_ROUTER",
    "Ros2Transport",
    "node_name_for",
    "open_router",
    "resolve_domain_id",
]

log = logging.getLogger("dbml.ros2")

DEFAULT_ROUTER = "tcp/localhost:7447"
"""Where rmw_zenoh's router of this host listens, and ROS 2 nodes connect."""
DEFAULT_LISTEN = "tcp/localhost:0"
"""Each session listens on a port of its own, so peers gossiped by the router link directly."""
PRIORITY_SUFFIX = "/dbm/priority"
"""A managed channel's priority topic (``std_msgs/msg/Float64``) and parameter."""
_OPTIMIZED_SUFFIX = "/optimized"
_NODE_PREFIX = "dbml_"
_NOT_IN_NAME = re.compile(r"[^A-Za-z0-9_]")
_DBML_NODE = "dbml/node"
_DBML_NODE_KEY_PARTS = 4
"""``dbml/node/<node id>/<zenoh id>``."""
_MAX_LOGGED = 1024
"""Malformed keys remembered so each is logged once; beyond this, no more are logged."""
_NODE_ENTITY = 0
"""rmw_zenoh's node token repeats the node's id as its entity id."""
_HOST_PREFIX = "ros2:"


def resolve_domain_id(domain_id: int | None = None) -> int:
    """The ROS 2 domain: the argument, else ``ROS_DOMAIN_ID``, else 0 (checked: 0..232)."""
    if domain_id is not None:
        return check_domain_id(domain_id)
    return check_domain_id(os.environ.get("ROS_DOMAIN_ID") or 0)


def node_name_for(host: str) -> str:
    """The ROS 2 node name of dbml on ``host``: ``dbml_`` and the host, as a legal name."""
    return _NODE_PREFIX + _NOT_IN_NAME.sub("_", host)


def _guarded(callback: Callable[[zenoh.Sample], None]) -> Callable[[zenoh.Sample], None]:
    """``callback`` for zenoh's thread: input from the network must never kill it."""

    def run(sample: zenoh.Sample) -> None:
        try:
            callback(sample)
        except Exception:
            log.exception("ignoring %s: it could not be handled", str(sample.key_expr)[:160])

    return run


class _LogOnce:
    """Logs each distinct problem once: the network may repeat a bad key or value forever."""

    def __init__(self) -> None:
        self._seen: set[str] = set()
        self._lock = threading.Lock()

    def warning(self, key: str, message: str, *args: object) -> None:
        with self._lock:
            if key in self._seen or len(self._seen) >= _MAX_LOGGED:
                return
            self._seen.add(key)
        log.warning(message, *args)


class _Ros2Publisher:
    """One rmw-style publisher: typed key, rmw's attachment, an ``MP`` token while it lives."""

    def __init__(
        self,
        session: zenoh.Session,
        topic: str,
        key: str,
        token: zenoh.LivelinessToken,
        on_close: Callable[[], None],
    ) -> None:
        self.topic = topic
        self._publisher = session.declare_publisher(
            key, congestion_control=zenoh.CongestionControl.DROP
        )
        status = self._publisher.matching_status  # typed a bool, a MatchingStatus at runtime
        self._matching = bool(getattr(status, "matching", status))
        self._listener = self._publisher.declare_matching_listener(self._on_matching)
        self._token = token
        self._gid = uuid.uuid4().bytes
        self._sequence = 0
        self._lock = threading.Lock()
        self._on_close: Callable[[], None] | None = on_close

    def _on_matching(self, status: zenoh.MatchingStatus) -> None:
        self._matching = status.matching

    def put(self, payload: bytes, attachment: bytes | None = None) -> None:
        """Send CDR ``payload`` with rmw's attachment; dbml's ``attachment`` has no place here."""
        with self._lock:
            self._sequence += 1
            sequence = self._sequence
        rmw = encode_attachment(Attachment(sequence, time.time_ns(), self._gid))
        self._publisher.put(payload, attachment=rmw)

    @property
    def has_subscribers(self) -> bool:
        """Whether a subscriber's key matches, ROS 2's or dbml's."""
        return self._matching

    def close(self) -> None:
        """Undeclare the publisher and withdraw its token."""
        on_close, self._on_close = self._on_close, None
        if on_close is None:
            return
        for declared in (self._listener, self._publisher, self._token):
            _undeclare(declared)
        on_close()


def _undeclare(
    declared: zenoh.Subscriber[None]
    | zenoh.LivelinessToken
    | zenoh.Publisher
    | zenoh.MatchingListener[None],
) -> None:
    # A closed session has undeclared everything already.
    with contextlib.suppress(zenoh.ZError):
        declared.undeclare()  # type: ignore[no-untyped-call]  # the stubs leave it unannotated


class _Ros2Graph:
    """dbml's graph plus the ROS 2 subscriptions of managed channels' ``/optimized`` topics."""

    def __init__(self, inner: GraphView) -> None:
        self._inner = inner
        self._lock = threading.Lock()
        self._foreign: dict[str, tuple[str, GraphEntry]] = {}
        """ROS 2 subscriptions by token key: the session's zid and the entry."""
        self.watchers: CallbackList[[]] = CallbackList()

    def announce(self, role: Role, topic: str, variant: Variant) -> Handle:
        """Declare in dbml's graph (ROS 2 tokens are the endpoints' own)."""
        return self._inner.announce(role, topic, variant)

    def entries(self) -> frozenset[GraphEntry]:
        """Dbml's entries and the ROS 2 subscribers of ``/optimized`` topics."""
        with self._lock:
            foreign = frozenset(entry for _, entry in self._foreign.values())
        return self._inner.entries() | foreign

    def watch(self, callback: Callable[[], None]) -> Handle:
        """Call ``callback()`` on any change, dbml's or ROS 2's."""
        inner = self._inner.watch(callback)
        own = self.watchers.add(callback)

        def stop() -> None:
            inner.close()
            own.close()

        return Closer(stop)

    def add(self, key: str, zid: str, entry: GraphEntry) -> None:
        with self._lock:
            if key in self._foreign:
                return
            self._foreign[key] = (zid, entry)
        self.watchers.fire()

    def remove(self, key: str) -> None:
        with self._lock:
            if self._foreign.pop(key, None) is None:
                return
        self.watchers.fire()

    def forget_session(self, zid: str) -> None:
        """Drop what a session turned out to be dbml's declared: dbml's graph has it already."""
        with self._lock:
            keys = [key for key, (owner, _) in self._foreign.items() if owner == zid]
            for key in keys:
                del self._foreign[key]
        if keys:
            self.watchers.fire()


class Ros2Transport(TransportBase):
    """dbml over rmw_zenoh's wire format; a ``ZenohTransport`` carries dbml's own keys.

    Payloads are CDR already (``camera_frame`` makes a ``sensor_msgs/msg/Image``); a topic's
    type is ``set_topic_type``'s, else ``sensor_msgs/msg/Image``. Always ``close()`` it.
    """

    def __init__(
        self,
        *,
        host: str | None = None,
        connect: Sequence[str] = (),
        listen: Sequence[str] = (),
        config_file: str | Path | None = None,
        domain_id: int | None = None,
        ros_distro: str | None = None,
        msg_paths: Sequence[str | Path] = (),
        follow_all_params: bool = True,
    ) -> None:
        self.domain_id = resolve_domain_id(domain_id)
        self.types = MessageTypes(distro=ros_distro, msg_paths=msg_paths)
        if not (connect or listen or config_file):
            connect, listen = [DEFAULT_ROUTER], [DEFAULT_LISTEN]
        self._dbml = ZenohTransport(
            host=host,
            connect=connect,
            listen=listen,
            config_file=config_file,
            follow_all_params=follow_all_params,
        )
        self.host = self._dbml.host
        self.session = self._dbml.session
        self.zid = str(self.session.info.zid())
        self.node_name = node_name_for(self.host)
        self._graph = _Ros2Graph(self._dbml.graph)
        self._lock = threading.Lock()
        self._changed = threading.Condition(self._lock)
        self._closed = False
        self._log = _LogOnce()
        self._declared_types: dict[str, str] = {}
        self._seen_types: dict[str, tuple[str, str]] = {}
        """ROS 2 publishers by token key: topic and type (``topic_type``'s answers)."""
        self._dbml_zids: set[str] = {self.zid}
        self._entity = _NODE_ENTITY
        self._handles: set[Handle] = set()
        self._priorities: dict[str, tuple[Handle, int]] = {}
        """Managed channels' priority subscriptions, and how many publishers share each."""
        liveliness = self.session.liveliness()
        self._node_token = liveliness.declare_token(self._token(TokenKind.NODE).key())
        self._subscribers = [
            liveliness.declare_subscriber(f"{_DBML_NODE}/**", self._on_dbml_node, history=True),
            liveliness.declare_subscriber(
                f"{ADMIN_SPACE}/{self.domain_id}/**", _guarded(self._on_token), history=True
            ),
        ]

    # -- the parts dbml's own session provides ------------------------------------------------

    @property
    def params(self) -> ParamStore:
        """Dbml's replicated parameter store, as over zenoh."""
        return self._dbml.params

    @property
    def graph(self) -> _Ros2Graph:
        """Dbml's graph and ROS 2's subscriptions of managed topics."""
        return self._graph

    def now(self) -> float:
        """Monotonic seconds."""
        return time.monotonic()

    def wait_for_peers(self, timeout_s: float) -> bool:
        """Wait for another dbml session and what it owns (ROS 2 nodes own no parameters)."""
        return self._dbml.wait_for_peers(timeout_s)

    def confirm_param(self, name: str, *, timeout_s: float) -> bool:
        """Whether another dbml session holds our latest write of ``name``."""
        return self._dbml.confirm_param(name, timeout_s=timeout_s)

    def refresh(self, entry: GraphEntry) -> None:
        """Ask the dbml session that made ``entry`` again for its values."""
        if not entry.host.startswith(_HOST_PREFIX):
            self._dbml.refresh(entry)

    # -- types --------------------------------------------------------------------------------

    def set_topic_type(self, topic: str, msg_type: str) -> None:
        """Type ``topic`` (all its variants, or one: ``/x/optimized``) as ``msg_type``."""
        check_topic(topic)
        self.types.type_hash(msg_type)
        with self._lock:
            self._declared_types[topic] = msg_type

    def _type_of(self, topic: str, variant: Variant = Variant.FULL) -> tuple[str, str]:
        with self._lock:
            msg_type = self._declared_types.get(variant.key(topic)) or self._declared_types.get(
                topic, IMAGE_TYPE
            )
        return msg_type, self.types.type_hash(msg_type)

    def camera_frame(self, topic: str, size_bytes: int) -> bytes:
        """A ``sensor_msgs/msg/Image`` serialised to exactly ``size_bytes`` (52 at least)."""
        check_topic(topic)
        frame = image_cdr(size_bytes, stamp_ns=time.time_ns())
        with self._lock:
            msg_type = self._declared_types.setdefault(topic, IMAGE_TYPE)
        if msg_type != IMAGE_TYPE:
            raise TransportError(f"topic {topic!r} has type {msg_type!r}, not {IMAGE_TYPE!r}")
        return frame

    def topic_type(self, topic: str, *, timeout_s: float) -> str | None:
        """The type a ROS 2 publisher of ``topic`` declares, waiting up to ``timeout_s``."""
        check_topic(topic)

        def found() -> str | None:
            for seen_topic, msg_type in self._seen_types.values():
                if seen_topic == topic:
                    return msg_type
            return None

        with self._changed:
            self._changed.wait_for(lambda: found() is not None, timeout=timeout_s)
            return found()

    # -- topics -------------------------------------------------------------------------------

    def _token(
        self, kind: TokenKind, topic: str | None = None, msg_type: str | None = None
    ) -> LivelinessToken:
        with self._lock:
            entity = self._entity = self._entity + (kind is not TokenKind.NODE)
        return LivelinessToken(
            self.domain_id,
            self.zid,
            _NODE_ENTITY,
            entity,
            kind,
            self.node_name,
            topic=topic,
            msg_type=msg_type,
            type_hash=None if msg_type is None else self.types.type_hash(msg_type),
            qos=None if topic is None else QOS_RELIABLE_VOLATILE_KEEP_LAST_10,
        )

    def declare_publisher(self, topic: str, variant: Variant = Variant.FULL) -> _Ros2Publisher:
        """A ROS 2 publisher of ``topic``'s ``variant``; a managed one hears its priority topic."""
        check_topic(topic)
        name = variant.key(topic)
        msg_type, type_hash = self._type_of(topic, variant)
        token = self.session.liveliness().declare_token(
            self._token(TokenKind.PUBLISHER, name, msg_type).key()
        )
        managed = variant is Variant.OPTIMIZED
        if managed:
            self._hear_priority(topic)

        def closed() -> None:
            with self._lock:
                self._handles.discard(publisher)
            if managed:
                self._unhear_priority(topic)

        publisher = _Ros2Publisher(
            self.session,
            topic,
            data_key(self.domain_id, name, msg_type, type_hash),
            token,
            closed,
        )
        with self._lock:
            self._handles.add(publisher)
        return publisher

    def _subscribe_key(
        self, name: str, key: str, msg_type: str, on_sample: Callable[[zenoh.Sample], None]
    ) -> Handle:
        token = self.session.liveliness().declare_token(
            self._token(TokenKind.SUBSCRIPTION, name, msg_type).key()
        )
        subscriber = self.session.declare_subscriber(key, on_sample)

        def undeclare() -> None:
            _undeclare(subscriber)
            _undeclare(token)
            with self._lock:
                self._handles.discard(handle)

        handle = Closer(undeclare)
        with self._lock:
            self._handles.add(handle)
        return handle

    def subscribe(
        self, topic: str, callback: Callable[[Sample], None], variant: Variant = Variant.FULL
    ) -> Handle:
        """Call ``callback`` for every message of ``topic``'s ``variant``, whatever its type.

        The sample's attachment is rmw's 33 bytes (``ros2msg.decode_attachment``), not dbml's.
        """
        check_topic(topic)
        name = variant.key(topic)
        msg_type, _ = self._type_of(topic, variant)

        def on_sample(sample: zenoh.Sample) -> None:
            attachment = sample.attachment
            callback(
                Sample(
                    topic,
                    sample.payload.to_bytes(),
                    None if attachment is None else attachment.to_bytes(),
                )
            )

        any_type = f"{self.domain_id}/{name.removeprefix('/')}/*/*"
        return self._subscribe_key(name, any_type, msg_type, on_sample)

    # -- priority from ROS 2 ------------------------------------------------------------------

    def _hear_priority(self, topic: str) -> None:
        with self._lock:
            held = self._priorities.get(topic)
            if held is not None:
                self._priorities[topic] = (held[0], held[1] + 1)
                return
        name = topic + PRIORITY_SUFFIX
        key = data_key(self.domain_id, name, FLOAT64_TYPE, self.types.type_hash(FLOAT64_TYPE))

        def on_sample(sample: zenoh.Sample) -> None:
            self._on_priority(name, sample.payload.to_bytes())

        handle = self._subscribe_key(name, key, FLOAT64_TYPE, _guarded(on_sample))
        with self._lock:
            self._priorities[topic] = (handle, 1)

    def _unhear_priority(self, topic: str) -> None:
        with self._lock:
            handle, count = self._priorities.get(topic, (None, 0))
            if handle is None:
                return
            if count > 1:
                self._priorities[topic] = (handle, count - 1)
                return
            del self._priorities[topic]
        handle.close()

    def _on_priority(self, name: str, payload: bytes) -> None:
        """Apply a ROS 2 priority in [0, 1]; log anything else (never raise on zenoh's thread)."""
        try:
            value = decode_float64(payload)
        except TransportError as err:
            log.warning("%s: ignoring an undecodable priority: %s", name, err)
            return
        if not 0.0 <= value <= 1.0:  # NaN fails both comparisons
            log.warning("%s: ignoring priority %r: it must be a number in [0, 1]", name, value)
            return
        self.params.set(name, value)

    # -- ROS 2's graph ------------------------------------------------------------------------

    def _on_dbml_node(self, sample: zenoh.Sample) -> None:
        parts = str(sample.key_expr).split("/")
        if len(parts) != _DBML_NODE_KEY_PARTS or sample.kind != zenoh.SampleKind.PUT:
            return  # dbml's own transport logs malformed ones; a gone session's tokens go too
        zid = parts[3]
        with self._lock:
            if zid in self._dbml_zids:
                return
            self._dbml_zids.add(zid)
        self._graph.forget_session(zid)

    def _on_token(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        if sample.kind != zenoh.SampleKind.PUT:
            with self._changed:
                self._seen_types.pop(key, None)
            self._graph.remove(key)
            return
        try:
            token = parse_token(key)
        except TransportError as err:
            self._log.warning(key, "ignoring a malformed ROS 2 token: %s", err)
            return
        if token.domain_id != self.domain_id or token.topic is None or token.msg_type is None:
            return
        if token.kind is TokenKind.PUBLISHER:
            with self._changed:
                self._seen_types[key] = (token.topic, token.msg_type)
                self._changed.notify_all()
            return
        if token.kind is not TokenKind.SUBSCRIPTION or not token.topic.endswith(_OPTIMIZED_SUFFIX):
            return
        with self._lock:
            if token.zid in self._dbml_zids:
                return  # a dbml session: dbml's graph counts its subscriptions already
        channel = token.topic.removesuffix(_OPTIMIZED_SUFFIX)
        try:
            check_topic(channel)
        except TransportError:
            self._log.warning(key, "ignoring a ROS 2 subscription of %r", token.topic)
            return
        uid = f"{_HOST_PREFIX}{token.zid}/{token.node_id}/{token.entity_id}"
        entry = GraphEntry(
            Role.SUBSCRIBER, _HOST_PREFIX + token.zid, channel, Variant.OPTIMIZED, uid
        )
        self._graph.add(key, token.zid, entry)

    def close(self) -> None:
        """Withdraw every ROS 2 declaration, then close dbml's session."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            handles = list(self._handles)
            self._changed.notify_all()
        for handle in handles:
            handle.close()
        for subscriber in self._subscribers:
            _undeclare(subscriber)
        _undeclare(self._node_token)
        self._dbml.close()
