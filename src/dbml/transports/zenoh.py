"""The zenoh transport: the default real engine (eclipse-zenoh, peer mode).

With no flags, processes on one machine find each other over loopback without multicast: each
session tries to listen on a well-known port (non-fatal if taken) and on a port of its own, and
connects to the well-known port with retry; gossip then meshes everyone, and a newcomer re-forms
the rendezvous if its holder exits. ``connect`` / ``listen`` endpoints, or a zenoh config file,
span machines. Shared memory is off unless asked for: it would bypass any shaped link.

Key layout: topic ``/r1/camera`` is key ``r1/camera`` (and ``r1/camera/optimized``); parameter
``/r1/camera/dbm/priority`` is ``dbml/param/r1/camera/dbm/priority``; graph declarations are
liveliness tokens ``dbml/graph/<role>/<host>/<uid>/<variant>/<topic>``; each session is a token
``dbml/node/<node id>/<zenoh id>``. Parameters: a session caches every write
(``dbml/param/**``, and the optimizer's batches on ``dbml/batch``) and serves what it owns under
``dbml/own/<node id>/**``. A session opened with ``follow_all_params=False`` (a process that
only publishes) hears the global parameters (``dbml/param/dbm/**``), the batches, and the
parameters of the channels it writes to: the reports of a fleet's other publishers (bounds,
sizes, acknowledgements on every rate change) then cost it nothing. Two sessions that meet
(see each other's token, and again when their direct link comes up) each fetch what the other
owns and tell the other to fetch theirs, so what one wrote before the other could hear it is
not lost; after that, writes reach it (``dbml.transports.paramstore``).
"""

from __future__ import annotations

import contextlib
import logging
import os
import queue
import re
import threading
import time
import uuid
import weakref
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import TypeAlias

from dbml.core.errors import TransportError
from dbml.transports.base import (
    Closer,
    GraphEntry,
    Handle,
    Role,
    Sample,
    TransportBase,
    TransportPriority,
    Variant,
    check_topic,
    resolve_host,
)
from dbml.transports.callbacks import CallbackList
from dbml.transports.paramstore import (
    BATCH_KEY,
    PARAM_PREFIX,
    ReplicatedParams,
    decode_param,
)

try:
    import zenoh
except ImportError as err:  # pragma: no cover - eclipse-zenoh is a declared dependency
    raise TransportError(
        "the zenoh transport needs eclipse-zenoh: pip install 'eclipse-zenoh>=1.10'"
    ) from err

__all__ = [
    "DEFAULT_PORT",
    "PRIORITY_LINK_RANGES",
    "ZENOH_PRIORITY",
    "ZenohTransport",
    "open_router",
]

log = logging.getLogger("dbml.zenoh")

_OPEN: weakref.WeakSet[ZenohTransport] = weakref.WeakSet()
"""Transports not closed yet; a closed (or forgotten) one is not kept alive for the exit hook."""


def _close_open_transports() -> None:
    for transport in list(_OPEN):
        transport.close()


# zenoh's callback threads are not daemons: close the sessions before the interpreter joins its
# threads at exit (``atexit`` would run too late; this private hook runs first, where it exists).
_register = getattr(threading, "_register_atexit", None)
if _register is not None:
    _register(_close_open_transports)

DEFAULT_PORT = 17447
"""The loopback rendezvous port of the no-flags mode; ``DBML_ZENOH_PORT`` overrides it."""

CONFIRM_QUERY_S = 0.5
"""The longest one query of ``confirm_param`` waits for replies before it asks again."""
CONFIRM_POLL_S = 0.05
"""The pause between two queries of ``confirm_param``."""

SYNC_TIMEOUT_S = 2.0
"""How long the query for a newly met session's values waits for its answers."""
LINK_POLL_S = 0.25
"""How often a session looks for direct links that have just come up."""
MEET_AGAIN_S = 1.0
"""When two sessions that met meet once more (writes lost to a route not yet up come back)."""

ZENOH_PRIORITY: dict[TransportPriority, zenoh.Priority] = {
    TransportPriority.REAL_TIME: zenoh.Priority.REAL_TIME,
    TransportPriority.INTERACTIVE_HIGH: zenoh.Priority.INTERACTIVE_HIGH,
    TransportPriority.INTERACTIVE_LOW: zenoh.Priority.INTERACTIVE_LOW,
    TransportPriority.DATA_HIGH: zenoh.Priority.DATA_HIGH,
    TransportPriority.DATA: zenoh.Priority.DATA,
    TransportPriority.DATA_LOW: zenoh.Priority.DATA_LOW,
    TransportPriority.BACKGROUND: zenoh.Priority.BACKGROUND,
}
"""dbml's transport classes are zenoh's, one to one."""

_GRAPH = "dbml/graph"
_NODE = "dbml/node"
_CONTROL = zenoh.Priority.INTERACTIVE_HIGH
"""Parameter writes, queries and answers go ahead of bulk data (zenoh's DATA priority)."""
_GLOBALS = "/dbm"
"""The global parameters' names start with this (``/dbm/max_bandwidth_in_mbit``)."""
_CHANNEL_PARAMS = "/dbm/"
"""A channel's parameters are ``<topic>/dbm/<field>``."""
_OWN = "dbml/own"
"""Each session serves what it owns under ``dbml/own/<node id>/<name>``."""
_OWN_ANY = _OWN + "/*"
_OWN_KEY_PARTS = 4
"""``dbml/own/<node id>/<name without its leading slash>``, split at the first three slashes."""
_HELD = "held"
"""The query parameter asking every session for the one value named, owned or not."""
_PULL = "pull"
"""The query parameter telling a session to fetch what the named session owns."""
_NODE_ID = re.compile(r"[0-9a-f]{16}")
_NODE_KEY_PARTS = 4
"""``dbml/node/<node id>/<zenoh id>``."""
"""A session's node id: 16 hex digits of a random UUID."""
_GRAPH_KEY_SPLITS = 6
"""``dbml/graph/<role>/<host>/<uid>/<variant>/<topic...>``: the topic keeps its slashes."""

_Undeclarable: TypeAlias = (
    "zenoh.Subscriber[None] | zenoh.Queryable[None] | zenoh.LivelinessToken"
    " | zenoh.Publisher | zenoh.MatchingListener[None]"
)
"""A zenoh object that ``undeclare()`` withdraws from the network."""
_Declaration: TypeAlias = (
    "zenoh.Subscriber[None] | zenoh.Queryable[None] | zenoh.LivelinessToken | _ZenohPublisher"
)
"""Anything the session declared for this transport, kept alive until it is closed."""


def _data_key(topic: str, variant: Variant) -> str:
    return variant.key(check_topic(topic))[1:]


def _config(
    *,
    connect: Iterable[str],
    listen: Iterable[str],
    config_file: str | Path | None,
    shared_memory: bool,
    port: int,
    priority_links: bool = False,
) -> zenoh.Config:
    connect, listen = list(connect), list(listen)
    try:
        config = zenoh.Config.from_file(str(config_file)) if config_file else zenoh.Config()

        def put(key: str, value: str) -> None:
            config.insert_json5(key, value)

        if not config_file:
            put("mode", '"peer"')
        put("scouting/multicast/enabled", "false")
        put("scouting/delay", "0")
        put("transport/shared_memory/enabled", "true" if shared_memory else "false")
        if priority_links:
            put("transport/unicast/max_links", str(len(PRIORITY_LINK_RANGES)))
        if connect or listen:
            if listen:
                put("listen/endpoints", _json_list(listen, listening=True))
            if connect:
                put(
                    "connect/endpoints",
                    _json_list(_priority_endpoints(connect) if priority_links else connect),
                )
                put("connect/exit_on_failure", "false")
                put("connect/timeout_ms", "-1")
                put("connect/retry", "{period_init_ms: 100, period_max_ms: 1000}")
        elif not config_file:
            rendezvous = f"tcp/127.0.0.1:{port}"
            put("listen/endpoints", _json_list([rendezvous, "tcp/127.0.0.1:0"], listening=True))
            put("listen/exit_on_failure", "false")
            put("listen/timeout_ms", "0")  # never retry a listen: close() would hang 10 s
            put("connect/endpoints", _json_list([rendezvous]))
            put("connect/exit_on_failure", "false")
            put("connect/timeout_ms", "-1")
            put("connect/retry", "{period_init_ms: 100, period_max_ms: 500}")
    except (zenoh.ZError, OSError) as err:
        raise TransportError(f"zenoh config: {err}") from err
    return config


PRIORITY_LINK_RANGES = ("1-3", "4-7")
"""With ``priority_links``, one link per range of zenoh priorities (1 = real_time ...
7 = background): real_time to interactive_low (control traffic and small urgent messages),
then data_high to background (every camera frame, whatever its channel's priority). zenoh sends
a message on the link whose range holds its priority, so an urgent message has a TCP connection
of its own and never waits behind bulk bytes already in the other's socket buffer (measured in
the testbed: p95 34 ms instead of 995 ms beside saturating cameras)."""


def _priority_endpoints(endpoints: Iterable[str]) -> list[str]:
    """Each endpoint once per ``PRIORITY_LINK_RANGES`` (``tcp/a:7447?prio=1-3`` ...).

    An endpoint that already has metadata (``?...``) is kept as given: its author chose.
    """
    expanded: list[str] = []
    for endpoint in endpoints:
        locator, hash_, config = endpoint.partition("#")
        if "?" in locator:
            expanded.append(endpoint)
            continue
        expanded.extend(f"{locator}?prio={r}{hash_}{config}" for r in PRIORITY_LINK_RANGES)
    return expanded


_PORTED = frozenset({"tcp", "udp", "tls", "quic", "ws"})
"""Endpoint protocols whose address ends in ``:PORT``."""
_MAX_PORT = 65_535


def _json_list(items: list[str], *, listening: bool = False) -> str:
    """Endpoints as a JSON list, each checked.

    A malformed one, or a port out of range, is refused here rather than leaving a session that
    silently reaches no one.
    """
    for item in items:
        protocol, slash, address = item.partition("/")
        if not slash or not address or '"' in item:
            raise TransportError(f"endpoint={item!r} must look like 'tcp/192.168.1.2:7447'")
        if protocol in _PORTED:
            # The port ends where zenoh's metadata (``?prio=1-4``) or config (``#iface=``) start.
            located = address.partition("#")[0].partition("?")[0]
            _, colon, port = located.rpartition(":")
            lowest = 0 if listening else 1  # port 0: any free port, for a listener only
            if not colon or not port.isdigit() or not lowest <= int(port) <= _MAX_PORT:
                raise TransportError(
                    f"endpoint={item!r}: the port must be {lowest}-{_MAX_PORT}, "
                    "as in 'tcp/192.168.1.2:7447'"
                )
    return "[" + ", ".join(f'"{item}"' for item in items) + "]"


def _undeclare(declared: _Undeclarable) -> None:
    """Undeclare ``declared``; quietly when the session is closed already (it undeclared all)."""
    with contextlib.suppress(zenoh.ZError):
        declared.undeclare()  # type: ignore[no-untyped-call]  # the stubs leave it unannotated


def _is_matching(status: object) -> bool:
    """Whether a publisher has subscribers, from what its matching status gives.

    The stubs type ``Publisher.matching_status`` as a bool while the library returns a
    ``MatchingStatus``; this reads either.
    """
    return bool(getattr(status, "matching", status))


class _ZenohPublisher:
    def __init__(
        self,
        session: zenoh.Session,
        topic: str,
        variant: Variant,
        on_close: Callable[[], None],
        *,
        priority: TransportPriority | None = None,
        express: bool = False,
    ) -> None:
        self.topic = topic
        # A zenoh publisher's class is fixed at declaration (``Publisher.put`` takes none).
        self._publisher = session.declare_publisher(
            _data_key(topic, variant),
            congestion_control=zenoh.CongestionControl.DROP,
            priority=None if priority is None else ZENOH_PRIORITY[priority],
            express=express,
        )
        self.has_subscribers = _is_matching(self._publisher.matching_status)
        """Kept current by zenoh's matching listener; a plain attribute, read per message."""
        self._listener = self._publisher.declare_matching_listener(self._on_matching)
        self._on_close = on_close
        # zenoh's own bound method: the hot path of a managed publish calls it directly.
        self.put: Callable[..., None] = self._publisher.put

    def _on_matching(self, status: zenoh.MatchingStatus) -> None:
        self.has_subscribers = status.matching

    def close(self) -> None:
        _undeclare(self._listener)
        _undeclare(self._publisher)
        self._on_close()


class _ZenohGraph:
    def __init__(self, transport: ZenohTransport) -> None:
        self._transport = transport
        self._lock = threading.Lock()
        self._entries: dict[str, GraphEntry] = {}
        # A dropped token is undeclared: keep each until it is withdrawn.
        self._tokens: dict[str, zenoh.LivelinessToken] = {}
        self.watchers: CallbackList[[]] = CallbackList()
        self._count = 0

    def announce(self, role: Role, topic: str, variant: Variant) -> Handle:
        check_topic(topic)
        transport = self._transport
        with self._lock:
            self._count += 1
            uid = f"{transport.node_id}.{self._count}"
        key = f"{_GRAPH}/{role.value}/{transport.host}/{uid}/{variant.value}{topic}"
        entry = GraphEntry(role, transport.host, topic, variant, uid)
        token = transport.session.liveliness().declare_token(key)
        with self._lock:
            self._entries[key] = entry
            self._tokens[key] = token
        self.watchers.fire()

        def withdraw() -> None:
            with self._lock:
                self._entries.pop(key, None)
                self._tokens.pop(key, None)
            _undeclare(token)
            self.watchers.fire()

        return Closer(withdraw)

    def entries(self) -> frozenset[GraphEntry]:
        with self._lock:
            return frozenset(self._entries.values())

    def watch(self, callback: Callable[[], None]) -> Handle:
        return self.watchers.add(callback)

    def on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        parts = key.split("/", _GRAPH_KEY_SPLITS)  # dbml graph role host uid variant topic...
        try:
            entry = GraphEntry(
                Role(parts[2]), parts[3], "/" + parts[6], Variant(parts[5]), parts[4]
            )
        except (IndexError, ValueError):
            log.warning("ignoring malformed graph token %s", key)
            return
        with self._lock:
            if sample.kind == zenoh.SampleKind.PUT:
                if key in self._entries:
                    return
                self._entries[key] = entry
            elif self._entries.pop(key, None) is None:
                return
        if sample.kind == zenoh.SampleKind.PUT:
            # A publisher declares its parameters before it announces itself: what its session
            # owns now includes them, even if their writes went out before they could reach us.
            self._transport.fetch_owner_of(entry.uid)
        self.watchers.fire()


class ZenohTransport(TransportBase):
    """A zenoh session wrapped as a dbml transport.

    Always ``close()`` it (or use ``with``): zenoh's callback threads keep the interpreter alive
    otherwise. ``priority_links`` opens one link per ``PRIORITY_LINK_RANGES`` to every
    ``connect`` endpoint (and accepts as many per peer): the classes a channel's priority maps
    to then overtake queued frames on a congested link, not only inside zenoh's queues.
    """

    has_priorities = True
    """Publishers are declared in zenoh's priority classes (and ``express``)."""

    def __init__(
        self,
        *,
        host: str | None = None,
        connect: Iterable[str] = (),
        listen: Iterable[str] = (),
        config_file: str | Path | None = None,
        shared_memory: bool = False,
        port: int | None = None,
        follow_all_params: bool = True,
        priority_links: bool = False,
    ) -> None:
        self.host = resolve_host(host)
        self.node_id = uuid.uuid4().hex[:16]
        if port is None:
            port = int(os.environ.get("DBML_ZENOH_PORT", DEFAULT_PORT))
        config = _config(
            connect=connect,
            listen=listen,
            config_file=config_file,
            shared_memory=shared_memory,
            port=port,
            priority_links=priority_links,
        )
        try:
            self.session: zenoh.Session = zenoh.open(config)
        except zenoh.ZError as err:
            raise TransportError(f"zenoh: cannot open a session: {err}") from err
        self._closed = False
        self._lock = threading.Lock()
        # Each declaration until it is closed: a dropped zenoh object is undeclared.
        self._declared: set[_Declaration] = set()
        self._peers = threading.Event()
        self._live: set[str] = set()
        """The dbml sessions met and still alive, by node id."""
        self._fetching = 0
        self._due: set[str] = set()
        """Sessions whose values a queued fetch will ask for."""
        self._zids: dict[str, str] = {}
        """The live sessions' zenoh ids, to their node ids."""
        self._linked: set[str] = set()
        """The zenoh ids this session has a direct link to, as last seen."""
        self._meet_again: list[tuple[float, str]] = []
        """Sessions to meet once more, and when."""
        self._synced = threading.Condition(self._lock)
        self._fetches: queue.SimpleQueue[tuple[str, bool] | None] = queue.SimpleQueue()
        self._replier = self.node_id.encode()
        self._follow_all = follow_all_params
        self._followed: set[str] = set()
        """The channels whose parameters this session hears, when it does not hear them all."""
        self.params = ReplicatedParams(self.node_id, send=self._send)
        self.graph = _ZenohGraph(self)
        threading.Thread(target=self._fetch_loop, name="dbml-param-sync", daemon=True).start()
        session = self.session
        heard = f"{PARAM_PREFIX}/**" if follow_all_params else f"{PARAM_PREFIX}{_GLOBALS}/**"
        self._declared |= {
            session.declare_subscriber(heard, self._on_param),
            session.declare_subscriber(BATCH_KEY, self._on_batch),
            session.declare_queryable(f"{_OWN}/{self.node_id}/**", self._on_query),
            session.liveliness().declare_subscriber(
                f"{_GRAPH}/**", self.graph.on_sample, history=True
            ),
            session.liveliness().declare_subscriber(f"{_NODE}/**", self._on_node, history=True),
            session.liveliness().declare_token(f"{_NODE}/{self.node_id}/{session.info.zid()}"),
        }
        _OPEN.add(self)

    # -- the parameter store's wire -----------------------------------------------------------

    def _send(self, key: str, data: bytes) -> None:
        """Put one parameter write or batch (on the store's sender thread, never a callback's).

        Control traffic: never dropped behind bulk data (which uses DROP), and sent ahead of it.
        A session that does not hear every parameter starts hearing a channel's when it first
        writes one of them (a publisher's bounds): others' writes there are its business.
        """
        if not self._follow_all:
            self._follow(key)
        self.session.put(
            key,
            data,
            congestion_control=zenoh.CongestionControl.BLOCK,
            priority=_CONTROL,
        )

    def _follow(self, key: str) -> None:
        """Hear the parameters of the channel that ``key`` (a parameter write's) belongs to."""
        if not key.startswith(PARAM_PREFIX + "/"):
            return
        end = key.find(_CHANNEL_PARAMS, len(PARAM_PREFIX))
        if end <= len(PARAM_PREFIX):  # a global parameter (heard already), or not a channel's
            return
        channel = key[: end + len(_CHANNEL_PARAMS)] + "**"
        with self._lock:
            if channel in self._followed or self._closed:
                return
            self._followed.add(channel)
        try:
            subscriber = self.session.declare_subscriber(channel, self._on_param)
        except zenoh.ZError:
            return  # closing: nothing left to hear
        with self._lock:
            if self._closed:
                _undeclare(subscriber)
                return
            self._declared.add(subscriber)
        # What others wrote there between the meetings' fetches and now, from its owners.
        own = f"{_OWN_ANY}/{channel[len(PARAM_PREFIX) + 1 :]}"
        self.session.get(
            own,
            zenoh.handlers.Callback(self._on_owned_reply, lambda: None),
            target=zenoh.QueryTarget.ALL,
            consolidation=zenoh.ConsolidationMode.NONE,
            timeout=SYNC_TIMEOUT_S,
            priority=_CONTROL,
        )

    def _on_owned_reply(self, reply: zenoh.Reply) -> None:
        """A value some session owns, from ``dbml/own/<node id><name>``."""
        sample = reply.ok
        if sample is None:
            return
        parts = str(sample.key_expr).split("/", 3)
        if len(parts) == _OWN_KEY_PARTS and _NODE_ID.fullmatch(parts[2]):
            self.params.on_value("/" + parts[3], sample.payload.to_bytes())

    def _on_param(self, sample: zenoh.Sample) -> None:
        self.params.on_write(str(sample.key_expr), sample.payload.to_bytes())

    def _on_batch(self, sample: zenoh.Sample) -> None:
        self.params.on_batch(sample.payload.to_bytes())

    def _is_live(self, node: str) -> bool:
        with self._lock:
            return node == self.node_id or node in self._live

    def _on_query(self, query: zenoh.Query) -> None:
        """Answer a query on this session's own key.

        Plain: what this session owns. ``?held``: the one value named, whoever owns it.
        ``?pull=<node>``: fetch what that session owns (it has just met this one).
        """
        own = f"{_OWN}/{self.node_id}"
        parameters = query.parameters
        if _HELD in parameters:
            key = str(query.key_expr)
            name = key[len(_OWN_ANY) :] if key.startswith(_OWN_ANY + "/") else ""
            data = self.params.held(name) if name else None
            if data is not None:
                query.reply(own + name, data, attachment=self._replier)
            return
        puller = parameters.get(_PULL)
        if puller is not None:
            self._schedule_fetch(puller)
            return
        for name, data in self.params.owned(self._is_live):
            reply_key = own + name
            if query.key_expr.intersects(reply_key):
                query.reply(reply_key, data, attachment=self._replier)

    def _on_node(self, sample: zenoh.Sample) -> None:
        parts = str(sample.key_expr).split("/")
        if len(parts) != _NODE_KEY_PARTS:
            log.warning("ignoring malformed session token %s", str(sample.key_expr)[:80])
            return
        node, zid = parts[2], parts[3]
        if node == self.node_id:
            return
        with self._lock:
            if sample.kind != zenoh.SampleKind.PUT:
                self._live.discard(node)
                if self._zids.get(zid) == node:
                    del self._zids[zid]
                return
            if node in self._live:
                return
            self._live.add(node)
            self._zids[zid] = node
        self._peers.set()
        self._meet(node)

    def _meet(self, node: str, *, again: bool = True) -> None:
        """Tell ``node`` to fetch what we own and fetch what it owns (off zenoh's thread).

        What we wrote before our writes could reach its subscriber is in that fetch; from then
        on our writes reach it. But a session's token can arrive before its subscriber's
        declaration (or, from a peer's answer, before the link to it is up), so the meeting is
        repeated once ``MEET_AGAIN_S`` later, and whenever a direct link to it comes up.
        """
        self._fetches.put((node, True))
        self._schedule_fetch(node)
        if again:
            with self._lock:
                self._meet_again.append((time.monotonic() + MEET_AGAIN_S, node))

    def _new_links(self) -> None:
        """Meet again the sessions whose direct link has just come up, or whose time came."""
        try:
            linked = {str(zid) for zid in self.session.info.peers_zid()}
        except zenoh.ZError:
            return
        now = time.monotonic()
        with self._lock:
            fresh = [self._zids[z] for z in linked - self._linked if z in self._zids]
            self._linked = linked
            due = [node for at, node in self._meet_again if at <= now and node in self._live]
            self._meet_again = [(at, node) for at, node in self._meet_again if at > now]
        for node in fresh:
            self._meet(node)
        for node in due:
            self._meet(node, again=False)

    def fetch_owner_of(self, uid: str) -> None:
        """Fetch what the session that made graph entry ``uid`` (``<node id>.<n>``) owns."""
        node = uid.partition(".")[0]
        if node != self.node_id:
            self._schedule_fetch(node)

    def refresh(self, entry: GraphEntry) -> None:
        """Meet the session that made ``entry`` again: both fetch what the other owns."""
        node = entry.uid.partition(".")[0]
        if node != self.node_id and _NODE_ID.fullmatch(node):
            self._meet(node, again=False)

    def _schedule_fetch(self, node: str) -> None:
        """Fetch ``node``'s values soon, once: a fetch already waiting covers this one too."""
        if not _NODE_ID.fullmatch(node):
            log.warning("ignoring a fetch request from a malformed node id %s", node[:40])
            return
        with self._lock:
            if node in self._due:
                return
            self._due.add(node)
            self._fetching += 1
        self._fetches.put((node, False))

    def _fetch_loop(self) -> None:
        """Ask sessions for their values, or to ask for ours; answers arrive on zenoh's threads.

        A failure is logged and the loop goes on: a dead loop would leave this session deaf to
        every value written before it could hear it.
        """
        while not self._closed:
            try:
                self._new_links()
                try:
                    item = self._fetches.get(timeout=LINK_POLL_S)
                except queue.Empty:
                    continue
                if item is None:
                    return
                self._fetch_one(*item)
            except Exception:
                if not self._closed:
                    log.exception("parameter sync")

    def _fetch_one(self, node: str, announce: bool) -> None:
        prefix = f"{_OWN}/{node}"
        if announce:
            self.session.get(
                f"{prefix}?{_PULL}={self.node_id}", lambda _reply: None, priority=_CONTROL
            )
            return
        with self._lock:
            self._due.discard(node)

        def on_reply(reply: zenoh.Reply) -> None:
            sample = reply.ok
            if sample is None:
                return
            key = str(sample.key_expr)
            if key.startswith(prefix + "/"):
                self.params.on_value(key[len(prefix) :], sample.payload.to_bytes())

        try:
            self.session.get(
                f"{prefix}/**",
                zenoh.handlers.Callback(on_reply, self._fetched),
                target=zenoh.QueryTarget.ALL,
                consolidation=zenoh.ConsolidationMode.NONE,
                timeout=SYNC_TIMEOUT_S,
                priority=_CONTROL,
            )
        except BaseException:
            self._fetched()
            raise

    def _fetched(self) -> None:
        with self._lock:
            self._fetching -= 1
            self._synced.notify_all()

    def wait_for_peers(self, timeout_s: float) -> bool:
        """Wait until another dbml session is reachable and what the sessions met own is here."""
        deadline = time.monotonic() + timeout_s
        if not self._peers.wait(timeout_s):
            return False
        with self._lock:
            self._synced.wait_for(
                lambda: self._fetching == 0, timeout=max(0.0, deadline - time.monotonic())
            )
        return True

    def confirm_param(self, name: str, *, timeout_s: float) -> bool:
        """Whether another session holds our latest write of ``name`` (polled, bounded)."""
        mine = self.params.stamp(name)
        if mine is None:
            return False
        check_topic(name)
        deadline = time.monotonic() + timeout_s
        if not self.params.flush(timeout_s):
            return False
        while (left := deadline - time.monotonic()) > 0:
            replies = self.session.get(
                f"{_OWN_ANY}{name}?{_HELD}",
                target=zenoh.QueryTarget.ALL,
                consolidation=zenoh.ConsolidationMode.NONE,
                timeout=min(CONFIRM_QUERY_S, left),
            )
            for reply in replies:
                sample = reply.ok
                if sample is None or sample.attachment is None:
                    continue
                if sample.attachment.to_bytes() == self._replier:
                    continue  # our own cache answering
                try:
                    _, stamp, writer = decode_param(sample.payload.to_bytes())
                except TransportError:
                    continue
                if (stamp, writer) == mine:
                    return True
            time.sleep(min(CONFIRM_POLL_S, max(0.0, deadline - time.monotonic())))
        return False

    # -- topics -------------------------------------------------------------------------------

    now = staticmethod(time.monotonic)
    """Monotonic seconds (the function itself: publishers read it per message)."""

    def _forget(self, declaration: _Declaration) -> None:
        with self._lock:
            self._declared.discard(declaration)

    def declare_publisher(
        self,
        topic: str,
        variant: Variant = Variant.FULL,
        *,
        priority: TransportPriority | None = None,
        express: bool = False,
    ) -> _ZenohPublisher:
        """A publisher of ``topic``; data, dropped rather than queued under congestion.

        ``priority`` is its zenoh class (None: zenoh's default, DATA), ``express`` sends each
        message at once instead of batching it.
        """
        check_topic(topic)
        publisher = _ZenohPublisher(
            self.session,
            topic,
            variant,
            on_close=lambda: self._forget(publisher),
            priority=priority,
            express=express,
        )
        with self._lock:
            self._declared.add(publisher)
        return publisher

    def subscribe(
        self, topic: str, callback: Callable[[Sample], None], variant: Variant = Variant.FULL
    ) -> Handle:
        """Call ``callback`` on zenoh's thread for every sample of ``topic`` in ``variant``."""
        key = _data_key(topic, variant)

        def on_sample(sample: zenoh.Sample) -> None:
            attachment = sample.attachment
            callback(
                Sample(
                    topic,
                    sample.payload.to_bytes(),
                    None if attachment is None else attachment.to_bytes(),
                )
            )

        subscriber = self.session.declare_subscriber(key, on_sample)
        with self._lock:
            self._declared.add(subscriber)

        def undeclare() -> None:
            _undeclare(subscriber)
            self._forget(subscriber)

        return Closer(undeclare)

    def close(self) -> None:
        """Send the queued parameter writes (bounded), then close the session."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
        self.params.close()
        self._fetches.put(None)
        with self._lock:
            self._declared.clear()
        _OPEN.discard(self)
        try:
            self.session.close()  # type: ignore[no-untyped-call]  # unannotated in the stubs
        except zenoh.ZError as err:
            log.warning("zenoh close: %s", err)


def open_router(listen: Iterable[str]) -> zenoh.Session:
    """A zenoh session in router mode listening on ``listen``, for hosts without rmw_zenohd.

    Clients and peers that connect to it are routed to each other. Multicast scouting and
    shared memory are off, as in every dbml session (shared memory would bypass a shaped link).
    A malformed endpoint, or one that cannot be listened on, is a ``TransportError`` naming it.
    """
    endpoints = list(listen)
    try:
        config = zenoh.Config()
        config.insert_json5("mode", '"router"')
        config.insert_json5("listen/endpoints", _json_list(endpoints, listening=True))
        config.insert_json5("scouting/multicast/enabled", "false")
        config.insert_json5("transport/shared_memory/enabled", "false")
        return zenoh.open(config)
    except zenoh.ZError as err:
        raise TransportError(f"zenoh router: cannot listen on {endpoints!r}: {err}") from err
