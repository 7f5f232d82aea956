"""The ros2 transport: rmw_zenoh's wire format on a zenoh session, beside dbml's own keys.

A managed ``[topic]/optimized`` is an ordinary ROS 2 topic: its messages travel under rmw_zenoh's
typed keys with its 33-byte attachment, and dbml's node, publishers and subscriptions declare
rmw_zenoh's liveliness tokens, so ``ros2 topic list``/``info`` show them with their types.
dbml's parameter store and graph (``dbml/**``) run unchanged in the same zenoh session
(``dbml.transports.zenoh``), so dbml processes over ``ros2`` and over ``zenoh`` still meet.

ROS 2 nodes take part without knowing dbml: a ROS 2 subscription of ``X/optimized`` appears in
the graph as a subscriber of channel ``X`` (so the optimizer manages it), and a ROS 2
publisher's token tells ``topic_type`` its type. Everything read from the network is validated;
a malformed token is logged once and ignored.

Topology as rmw_zenoh's: peer mode, connect to the router of this host (``tcp/localhost:7447``,
``dbml router`` or ``rmw_zenohd``), listen on a port of its own, no multicast, no shared memory.

Trust: a session whose dbml node token (``dbml.protocol.keys``) is live counts as dbml's, and its
ROS 2 subscriptions are left to dbml's graph. A peer may declare such a token for another session's
zid and so hide that session's ROS 2 subscribers (fewer managed channels, never more bytes);
the access control of ``dbml secure init`` (only dbml roles may declare ``dbml/**``) is the
real defence. Whatever is remembered of the network is capped, so a token flood stays bounded.
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
from dbml.protocol import keys
from dbml.transports.base import (
    DEFAULT_ROUTER_ENDPOINT,
    Closer,
    GraphEntry,
    GraphView,
    Handle,
    ParamStore,
    Role,
    Sample,
    TransportBase,
    TransportPriority,
    Variant,
    check_topic,
    of_topic,
)
from dbml.transports.callbacks import CallbackList
from dbml.transports.codecs import IMAGE_TYPE
from dbml.transports.overflow import LogOnce
from dbml.transports.ros2.wire import (
    ADMIN_SPACE,
    QOS_RELIABLE_VOLATILE_KEEP_LAST_10,
    Attachment,
    LivelinessToken,
    MessageTypes,
    TokenKind,
    check_domain_id,
    data_key,
    encode_attachment,
    parse_token,
)
from dbml.transports.zenoh.transport import ZENOH_PRIORITY, ZenohTransport

__all__ = [
    "DEFAULT_LISTEN",
    "Ros2Transport",
    "node_name_for",
    "resolve_domain_id",
]

log = logging.getLogger("dbml.ros2")

DEFAULT_LISTEN = "tcp/localhost:0"
"""Each session listens on a port of its own, so peers gossiped by the router link directly."""
_OPTIMIZED_SUFFIX = Variant.OPTIMIZED.key("")
_NODE_PREFIX = "dbml_"
_NOT_IN_NAME = re.compile(r"[^A-Za-z0-9_]")
_ZID = re.compile(r"[0-9a-f]{1,32}")
"""A zenoh id: up to 16 bytes in lower-case hex."""
_MAX_FOREIGN = 4096
"""ROS 2 subscriptions of ``/optimized`` topics remembered at most (beyond: ignored, logged)."""
_MAX_SEEN_TYPES = 4096
"""ROS 2 publishers' types remembered at most, for ``topic_type`` (beyond: ignored, logged)."""
_MAX_DBML_SESSIONS = 1024
"""dbml sessions remembered at most; beyond, their ROS 2 tokens may be counted twice."""
_MAX_NODES_PER_SESSION = 16
"""dbml node tokens remembered per session (one ``ZenohTransport`` declares one)."""
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


class _Ros2Publisher:
    """One rmw-style publisher: typed key, rmw's attachment, an ``MP`` token while it lives."""

    def __init__(
        self,
        session: zenoh.Session,
        topic: str,
        key: str,
        token: zenoh.LivelinessToken,
        on_close: Callable[[], None],
        *,
        priority: TransportPriority | None = None,
        express: bool = False,
    ) -> None:
        self.topic = topic
        self._publisher = session.declare_publisher(
            key,
            congestion_control=zenoh.CongestionControl.DROP,
            priority=None if priority is None else ZENOH_PRIORITY[priority],
            express=express,
        )
        try:
            status = self._publisher.matching_status  # typed a bool, a MatchingStatus at runtime
            self._matching = bool(getattr(status, "matching", status))
            self._listener = self._publisher.declare_matching_listener(self._on_matching)
        except BaseException:
            _undeclare(self._publisher)
            raise
        self._token = token
        self._gid = uuid.uuid4().bytes
        self._sequence = 0
        self._lock = threading.Lock()
        self._on_close: Callable[[], None] | None = on_close

    def _on_matching(self, status: zenoh.MatchingStatus) -> None:
        self._matching = status.matching

    def put(self, payload: bytes, *, attachment: bytes | None = None) -> None:
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
    """dbml's graph plus the ROS 2 subscriptions of managed channels' ``/optimized`` topics.

    It also knows which sessions are dbml's, under the same lock as the subscriptions, so a
    dbml session's token arriving between the check and the add of one of its ROS 2
    subscriptions cannot leave that subscription counted twice.
    """

    def __init__(self, inner: GraphView, own_zid: str) -> None:
        self._inner = inner
        self._own_zid = own_zid
        self._lock = threading.Lock()
        self._foreign: dict[str, tuple[str, GraphEntry]] = {}
        """ROS 2 subscriptions by token key: the session's zid and the entry."""
        self._dbml: dict[str, set[str]] = {}
        """Other dbml sessions by zid: the keys of their live node tokens."""
        self._full: set[str] = set()
        """Which caps were reached (each is logged once)."""
        self.watchers: CallbackList[[]] = CallbackList()

    def _reached(self, cap: str, limit: int) -> None:
        """Log once that ``cap`` is full; called under the lock, logs after."""
        if cap not in self._full:
            self._full.add(cap)
            log.warning("ignoring further %s: %d remembered already", cap, limit)

    def announce(self, role: Role, topic: str, variant: Variant) -> Handle:
        """Declare in dbml's graph (ROS 2 tokens are the endpoints' own)."""
        return self._inner.announce(role, topic, variant)

    def entries(self, *, topic: str | None = None) -> frozenset[GraphEntry]:
        """Dbml's entries and the ROS 2 subscribers of ``/optimized`` topics."""
        with self._lock:
            foreign = frozenset(entry for _, entry in self._foreign.values())
        return self._inner.entries(topic=topic) | of_topic(foreign, topic)

    def watch(self, callback: Callable[[], None], *, topic: str | None = None) -> Handle:
        """Call ``callback()`` on a change of dbml's (``topic``'s) or of ROS 2's (any)."""
        inner = self._inner.watch(callback, topic=topic)
        own = self.watchers.add(callback)

        def stop() -> None:
            inner.close()
            own.close()

        return Closer(stop)

    def is_dbml(self, zid: str) -> bool:
        """Whether ``zid`` is this or another live dbml session."""
        with self._lock:
            return zid == self._own_zid or zid in self._dbml

    def add(self, key: str, zid: str, entry: GraphEntry) -> None:
        """Count a ROS 2 subscription, unless its session is dbml's (or the cap is reached)."""
        with self._lock:
            if key in self._foreign or zid == self._own_zid or zid in self._dbml:
                return
            if len(self._foreign) >= _MAX_FOREIGN:
                self._reached("ROS 2 subscriptions", _MAX_FOREIGN)
                return
            self._foreign[key] = (zid, entry)
        self.watchers.fire()

    def remove(self, key: str) -> None:
        with self._lock:
            if self._foreign.pop(key, None) is None:
                return
        self.watchers.fire()

    def add_dbml(self, key: str, zid: str) -> None:
        """Session ``zid`` is dbml's (its node token ``key``): dbml's graph counts its entries."""
        with self._lock:
            tokens = self._dbml.get(zid)
            if tokens is None:
                if len(self._dbml) >= _MAX_DBML_SESSIONS:
                    self._reached("dbml sessions", _MAX_DBML_SESSIONS)
                    return
                tokens = self._dbml[zid] = set()
            if len(tokens) < _MAX_NODES_PER_SESSION:
                tokens.add(key)
            keys = [k for k, (owner, _) in self._foreign.items() if owner == zid]
            for k in keys:
                del self._foreign[k]
        if keys:
            self.watchers.fire()

    def remove_dbml(self, key: str, zid: str) -> None:
        """Node token ``key`` of session ``zid`` is gone; the last one ends it being dbml's."""
        with self._lock:
            tokens = self._dbml.get(zid)
            if tokens is None:
                return
            tokens.discard(key)
            if not tokens:
                del self._dbml[zid]


class Ros2Transport(TransportBase):
    """dbml over rmw_zenoh's wire format; a ``ZenohTransport`` carries dbml's own keys.

    Payloads are CDR already; a topic's type is ``set_topic_type``'s, else
    ``sensor_msgs/msg/Image``. Always ``close()`` it.
    """

    has_priorities = True
    """Publishers are declared in zenoh's priority classes (and ``express``)."""

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
        priority_links: bool = False,
    ) -> None:
        self.domain_id = resolve_domain_id(domain_id)
        self.types = MessageTypes(distro=ros_distro, msg_paths=msg_paths)
        if not (connect or listen or config_file):
            connect, listen = [DEFAULT_ROUTER_ENDPOINT], [DEFAULT_LISTEN]
        self._dbml = ZenohTransport(
            host=host,
            connect=connect,
            listen=listen,
            config_file=config_file,
            follow_all_params=follow_all_params,
            priority_links=priority_links,
        )
        try:
            self._declare(self._dbml)
        except BaseException:
            self._dbml.close()  # undeclares whatever was declared before the failure
            raise

    def _declare(self, dbml: ZenohTransport) -> None:
        """Everything but dbml's own session: split out so a failure here closes that session."""
        self.host = dbml.host
        self.session = dbml.session
        self.zid = str(self.session.info.zid())
        self.node_name = node_name_for(self.host)
        self._graph = _Ros2Graph(dbml.graph, self.zid)
        self._lock = threading.Lock()
        self._changed = threading.Condition(self._lock)
        self._closed = False
        self._log = LogOnce(log)
        self._declared_types: dict[str, str] = {}
        self._seen_types: dict[str, tuple[str, str, str]] = {}
        """ROS 2 publishers by token key: topic, type and type hash (``topic_type``'s answers)."""
        self._source_hashes: dict[str, str] = {}
        """Type hashes by type, as ``topic_type`` found them on publishers' tokens."""
        self._entity = _NODE_ENTITY
        self._handles: set[Handle] = set()
        liveliness = self.session.liveliness()
        self._node_token = liveliness.declare_token(self._token(TokenKind.NODE).key())
        self._subscribers = [
            liveliness.declare_subscriber(
                f"{keys.NODE}/**", _guarded(self._on_dbml_node), history=True
            ),
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

    now = staticmethod(time.monotonic)
    """Monotonic seconds (the function itself: publishers read it per message)."""

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
            declared = self._declared_types.setdefault(topic, msg_type)
        if declared != msg_type:
            raise TransportError(f"topic={topic!r} has type {declared!r}, not {msg_type!r}")

    def _type_of(self, topic: str, variant: Variant = Variant.FULL) -> tuple[str, str]:
        with self._lock:
            msg_type = self._declared_types.get(variant.key(topic)) or self._declared_types.get(
                topic, IMAGE_TYPE
            )
        return msg_type, self._hash_of(msg_type)

    def _hash_of(self, msg_type: str) -> str:
        """The hash a source publisher's token carries for ``msg_type``, else the typestore's.

        rmw_zenoh subscribes to the exact key, hash included: a bridge must republish under
        its source's hash, or subscribers of another distro never see ``/optimized``.
        """
        ours = self.types.type_hash(msg_type)  # also refuses a type the typestore lacks
        with self._lock:
            return self._source_hashes.get(msg_type, ours)

    def topic_type(self, topic: str, *, timeout_s: float) -> str | None:
        """The type a ROS 2 publisher of ``topic`` declares, waiting up to ``timeout_s``."""
        check_topic(topic)

        def found() -> tuple[str, str] | None:
            for seen_topic, msg_type, type_hash in self._seen_types.values():
                if seen_topic == topic:
                    return msg_type, type_hash
            return None

        with self._changed:
            self._changed.wait_for(lambda: found() is not None, timeout=timeout_s)
            seen = found()
            if seen is None:
                return None
            msg_type, type_hash = seen
            self._source_hashes[msg_type] = type_hash
        with contextlib.suppress(TransportError):  # a type unknown here is refused when used
            ours = self.types.type_hash(msg_type)
            if ours != type_hash:
                log.warning(
                    "%s: its publisher's %s hash %s is not the %s typestore's %s (another"
                    " distro?); republishing under the publisher's",
                    topic,
                    msg_type,
                    type_hash,
                    self.types.distro,
                    ours,
                )
        return msg_type

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
            type_hash=None if msg_type is None else self._hash_of(msg_type),
            qos=None if topic is None else QOS_RELIABLE_VOLATILE_KEEP_LAST_10,
        )

    def declare_publisher(
        self,
        topic: str,
        variant: Variant = Variant.FULL,
        *,
        priority: TransportPriority | None = None,
        express: bool = False,
    ) -> _Ros2Publisher:
        """A ROS 2 publisher of ``topic``'s ``variant``.

        ``priority`` and ``express`` are zenoh's, as for the zenoh transport (rmw_zenoh's
        subscribers read the data whatever its class).
        """
        check_topic(topic)
        name = variant.key(topic)
        msg_type, type_hash = self._type_of(topic, variant)
        token = self.session.liveliness().declare_token(
            self._token(TokenKind.PUBLISHER, name, msg_type).key()
        )

        def closed() -> None:
            with self._lock:
                self._handles.discard(publisher)

        try:
            publisher = _Ros2Publisher(
                self.session,
                topic,
                data_key(self.domain_id, name, msg_type, type_hash),
                token,
                closed,
                priority=priority,
                express=express,
            )
        except BaseException:
            _undeclare(token)
            raise
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

        The sample's attachment is rmw's 33 bytes (``wire.decode_attachment``), not dbml's.
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

    # -- ROS 2's graph ------------------------------------------------------------------------

    def _on_dbml_node(self, sample: zenoh.Sample) -> None:
        """Track which sessions are dbml's: only a well-formed node token makes one."""
        key = str(sample.key_expr)
        parsed = keys.parse_node_key(key)
        if parsed is None:
            return  # dbml's own transport logs malformed ones
        node_id, zid, _follows_all = parsed
        if not (keys.is_node_id(node_id) and _ZID.fullmatch(zid)):
            self._log.warning(key, "ignoring dbml node token %r: not <16 hex>/<zenoh id>", key)
            return
        if sample.kind == zenoh.SampleKind.PUT:
            self._graph.add_dbml(key, zid)
        else:
            self._graph.remove_dbml(key, zid)

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
            assert token.type_hash is not None  # parse_token requires it of an endpoint
            with self._changed:
                full = key not in self._seen_types and len(self._seen_types) >= _MAX_SEEN_TYPES
                if not full:
                    self._seen_types[key] = (token.topic, token.msg_type, token.type_hash)
                    self._changed.notify_all()
            if full:
                self._log.warning(
                    "<seen types full>",
                    "ignoring further ROS 2 publishers' types: %d remembered already",
                    _MAX_SEEN_TYPES,
                )
            return
        if token.kind is not TokenKind.SUBSCRIPTION or not token.topic.endswith(_OPTIMIZED_SUFFIX):
            return
        if self._graph.is_dbml(token.zid):
            return  # early out; ``add`` checks again under its lock
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
