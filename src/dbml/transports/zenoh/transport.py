"""The zenoh transport: the default real engine (eclipse-zenoh, peer mode).

With no flags, processes on one machine find each other over loopback without multicast: each
session tries to listen on a well-known port (non-fatal if taken) and on a port of its own, and
connects to the well-known port with retry; gossip then meshes everyone, and a newcomer re-forms
the rendezvous if its holder exits. ``connect`` / ``listen`` endpoints, or a zenoh config file,
span machines. Shared memory is off unless asked for: it would bypass any shaped link.

Key layout: the wire schema's (``dbml.protocol.keys``): a topic's data, parameter writes and
batches, each session's owned values (a queryable), graph declarations and sessions (liveliness
tokens). The parameter store's protocol over the session (meetings, fetches, confirmations) is
``dbml.transports.zenoh.params``; with ``follow_all_params=False`` (a process that only publishes)
a session hears the global parameters, the batches and the channels it writes to, and the graph
of the topics it subscribes to, so the reports of a fleet's other publishers (bounds, sizes,
acknowledgements, graph tokens) cost it nothing.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import threading
import time
import weakref
from collections import Counter
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import TypeAlias

from dbml.core.errors import TransportError
from dbml.protocol import keys
from dbml.protocol.names import PRIORITY_SUFFIX
from dbml.protocol.schema import split_channel_name
from dbml.transports.base import (
    EXPEDITED_TOS,
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
from dbml.transports.overflow import LogOnce, Overflow
from dbml.transports.zenoh.params import ParamSync

try:
    import zenoh
except ImportError as err:  # pragma: no cover - eclipse-zenoh is a declared dependency
    raise TransportError(
        "the zenoh transport needs eclipse-zenoh: pip install 'eclipse-zenoh>=1.10'"
    ) from err

__all__ = [
    "DEFAULT_PORT",
    "KEEP_ALIVES_PER_LEASE",
    "LEASE_MS",
    "MAX_GRAPH_ENTRIES",
    "NET_THREADS",
    "OPEN_TIMEOUT_MS",
    "PRIORITY_LINK_RANGES",
    "RETRY_MAX_MS",
    "ROUTER_RX_THREADS",
    "RUNTIME_ENV",
    "RX_THREADS",
    "ZENOH_PRIORITY",
    "ZenohTransport",
    "open_router",
    "prepare_runtime",
    "put_link_timeouts",
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
MAX_GRAPH_ENTRIES = 16_384
"""The most graph entries (publishers and subscribers) a session keeps from others' tokens.
A fleet of 160 robots with 4 channels each declares about four per channel (the publisher, a
local subscriber, the base station's of ``/optimized``, a monitor's): 2,560, six times less.
Any peer can declare tokens, so past this a new one is refused (its entry is not seen, its
owner's values not fetched for it) and logged once per flood, with a count; this process's own
declarations are always kept (its code bounds them). An entry costs a few hundred bytes."""

RX_THREADS = 32
"""Worker threads of zenoh's receiving runtime (zenoh's default: 2). zenoh sets a 10-s
``SO_LINGER`` on its TCP links and closes a link whose lease expired on that runtime, so the
close blocks its thread until the peer acknowledges what was still in flight, or 10 s pass.
After an outage longer than the lease, one such close per lost link held both default threads,
and no link was read, not even the new ones to the same peers (docs/testbed.md). With more
threads than links lost at once, the new links are read at once; past that number the rest
wait for a lingering close."""
ROUTER_RX_THREADS = 256
"""The receiving runtime's threads in a router (``open_router``). A router routes what a link
brings on that link's thread, and a reliable message (control traffic) to a session whose queue
is full waits there for room: a session that reads late holds one thread per link that sends to
it. A fleet of 80 x 4 starting at once, its router on ``RX_THREADS``, stopped reading its
links for 1-9 s (the optimizer's heartbeat reached every robot that late); the same run with
256 had a p99 of 0.19 s and no fail-safe (``bench/fleet.py``). A waiting thread costs no CPU."""
NET_THREADS = 4
"""Worker threads of zenoh's ``net`` runtime in a router (zenoh's default: 1), where a
``connect`` endpoint's attempts run, each under ``OPEN_TIMEOUT_MS``. A lost link's lingering
close (above) can land on that runtime's one thread: a router whose link to the base station's
had frames in flight when a 10-s outage dropped it gave up its first attempt after the link
returned 10.9 s after starting it, not 2 s, the close holding the thread that runs the
attempt's timer, and its robot was back 5.25 s after the link (the testbed's router topology
with a busy core beside it, as in CI: 2 of 16 runs). With 4 threads one runs the timer while
another lingers: 14 of 14 runs back within 1.5 s, two of them with such a close, their attempts
given up after 2.0 s. Every session: a peer's attempts run there too (with one thread, a robot
whose radio was out 10 s was back 4.75 s after it in two CI runs; not traced)."""
LEASE_MS = 3000
"""The lease dbml's sessions announce (zenoh's default: 10 s): a peer silent this long is closed
and opened anew. A session that outlives an outage resumes only when TCP's retransmission timer
next fires, and it doubles while the link is down (0.2, 0.6, 1.4, 3.0, 6.2, 12.6 s after the
first loss): with a 10-s lease, a 7-s outage would wait 5.6 s more. With 3 s the timer's next
expiry comes at most 1.6 s after a shorter outage ends, and a longer one reconnects with a fresh
connection."""
KEEP_ALIVES_PER_LEASE = 4
"""zenoh's keep-alives per lease (its default): one every 0.75 s on an idle link."""
OPEN_TIMEOUT_MS = 2000
"""The longest one attempt to open a link takes (zenoh's default: 10 s). A SYN lost in an
outage is sent again by TCP after 1, 3 and 7 s: an attempt given up after 2 s starts over with
a fresh SYN, so a returning link is found within about ``OPEN_TIMEOUT_MS`` + ``RETRY_MAX_MS``
instead of up to 4 s. A handshake takes a few round trips; 2 s leaves a radio link its due."""
PEER_MESH_SESSIONS = 50
"""The most sessions zenoh's peer mesh (dbml with no ``--connect``) was measured to complete on
a 2-core machine (``bench/mesh.py``, 10 sessions a process: 50 in 26 s; 60 not within 30 s, the
sessions holding 15-59 of their 59 links; 80 holding 0-79 of 79), and peers send only over
direct links. A session that meets more than this says so once, naming the router topology,
whose clients need one link each."""
RETRY_MAX_MS = 500
"""The longest pause between two attempts to reach a ``connect`` endpoint."""
RUNTIME_ENV = "ZENOH_RUNTIME"
"""zenoh's runtime settings (RON), read once when its first session opens."""


def prepare_runtime(*, rx_threads: int = RX_THREADS, net_threads: int = NET_THREADS) -> None:
    """Give zenoh's receiving runtime ``rx_threads`` threads (and ``net``: ``net_threads``).

    Call before the process's first session opens; later it changes nothing. Whoever set
    ``ZENOH_RUNTIME`` chose: it is left as it is.
    """
    settings = f"rx: (worker_threads: {rx_threads}), net: (worker_threads: {net_threads})"
    os.environ.setdefault(RUNTIME_ENV, f"({settings})")


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

_CONTROL = zenoh.Priority.INTERACTIVE_HIGH
"""Parameter writes, queries and answers go ahead of bulk data (zenoh's DATA priority)."""

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
    return keys.data_key(variant.key(topic))


def put_link_timeouts(config: zenoh.Config) -> None:
    """How soon a lost peer is dropped (``LEASE_MS``) and a returning one found."""
    config.insert_json5("transport/link/tx/lease", str(LEASE_MS))
    config.insert_json5("transport/link/tx/keep_alive", str(KEEP_ALIVES_PER_LEASE))
    config.insert_json5("transport/unicast/open_timeout", str(OPEN_TIMEOUT_MS))


def _config(
    *,
    connect: Iterable[str],
    listen: Iterable[str],
    config_file: str | Path | None,
    shared_memory: bool,
    port: int,
    host: str,
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
        if not config_file:  # a config file of the user's says its own
            put_link_timeouts(config)
        for kind, within in _aggregates(host).items():
            if config.get_json(f"aggregation/{kind}") == "[]":  # unless the user's file says
                put(f"aggregation/{kind}", json.dumps(within))
        if priority_links:
            put("transport/unicast/max_links", str(len(PRIORITY_LINK_RANGES)))
            if config.get_json("mode") == '"client"':
                log.warning(
                    "priority_links: a zenoh client opens one link, to the first router it "
                    "reaches; control and data share it (a peer opens one per range)"
                )
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
                put("connect/retry", f"{{period_init_ms: 100, period_max_ms: {RETRY_MAX_MS}}}")
        elif not config_file:
            rendezvous = f"tcp/127.0.0.1:{port}"
            put("listen/endpoints", _json_list([rendezvous, "tcp/127.0.0.1:0"], listening=True))
            put("listen/exit_on_failure", "false")
            put("listen/timeout_ms", "0")  # never retry a listen: close() would hang 10 s
            put("connect/endpoints", _json_list([rendezvous]))
            put("connect/exit_on_failure", "false")
            put("connect/timeout_ms", "-1")
            put("connect/retry", f"{{period_init_ms: 100, period_max_ms: {RETRY_MAX_MS}}}")
    except (zenoh.ZError, OSError) as err:
        raise TransportError(f"zenoh config: {err}") from err
    return config


PRIORITY_LINK_RANGES = ("1-3", "4-7")
"""With ``priority_links``, one link per range of zenoh priorities (1 = real_time ...
7 = background): real_time to interactive_low (control traffic and small urgent messages),
then data_high to background (every camera frame, whatever its channel's priority). zenoh sends
a message on the link whose range holds its priority, so an urgent message has a TCP connection
of its own and never waits behind bulk bytes already in the other's socket buffer. The first
range's link marks its packets ``EXPEDITED_TOS`` (DSCP EF), for the queues past the socket
(measured in the testbed beside saturating cameras, the link honouring DSCP: p95 3 ms instead of
775-1,012 ms; docs/testbed.md)."""
_DSCP_PROTOCOLS = frozenset({"tcp", "tls", "udp"})
"""zenoh sets a link's DSCP (``#dscp=``) on these only."""


def _priority_endpoints(endpoints: Iterable[str]) -> list[str]:
    """Each endpoint once per ``PRIORITY_LINK_RANGES`` (``tcp/a:7447?prio=1-3#dscp=0xb8`` ...).

    An endpoint that already has metadata (``?...``) is kept as given: its author chose; so is
    a ``dscp`` its config already names.
    """
    expanded: list[str] = []
    for endpoint in endpoints:
        locator, _, config = endpoint.partition("#")
        if "?" in locator:
            expanded.append(endpoint)
            continue
        for index, prio in enumerate(PRIORITY_LINK_RANGES):
            options = [option for option in config.split(";") if option]
            marked = any(option.partition("=")[0] == "dscp" for option in options)
            if index == 0 and not marked and locator.partition("/")[0] in _DSCP_PROTOCOLS:
                options.append(f"dscp={EXPEDITED_TOS:#x}")
            tail = f"#{';'.join(options)}" if options else ""
            expanded.append(f"{locator}?prio={prio}{tail}")
    return expanded


def _aggregates(host: str) -> dict[str, list[str]]:
    """What a session declares once for all it holds under its host's namespace (``/r1/...``).

    zenoh's ``aggregation``: the publishers of ``/r1/*`` topics share one interest in their
    subscribers, the subscriptions to those channels' parameters are one declaration and those
    to their priority topics another; the session sorts what arrives. A router matches each
    declaration against every other face's interests under one lock, so a fleet's own
    declarations held the heartbeat (160 robots x 4 channels: 27 declarations a robot, 14 so;
    docs/benchmarks.md). Topics outside the namespace are declared one by one, as before.
    """
    data = keys.data_key(f"/{host}")
    return {
        "publishers": [f"{data}/**"],
        "subscribers": [f"{keys.param_key(f'/{host}')}/**", f"{data}/**{PRIORITY_SUFFIX}"],
    }


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
    """The graph from the sessions' liveliness tokens.

    ``follow_all``: every topic's tokens (an optimizer, an operator, a monitor). Otherwise only
    the topics this session reads or watches (a subscriber's), each from its first use, and its
    own declarations: a robot that only publishes hears no graph, whatever the fleet's size.
    Every robot hearing every token cost a fleet of 80 x 4 57,000 callbacks at its start, and a
    subscription per topic declared costs the router: it routes under one lock, and declarations
    hold it (80 robots following their 4 topics each delayed every heartbeat by 1-4 s).
    """

    def __init__(self, transport: ZenohTransport, *, follow_all: bool = True) -> None:
        self._transport = transport
        self._follow_all = follow_all
        self._followed: set[str] = set()
        """The topics whose tokens are followed, when not all are (this process's own)."""
        self._lock = threading.Lock()
        self._entries: dict[str, GraphEntry] = {}
        """Every live entry by token key: ours and, up to ``MAX_GRAPH_ENTRIES``, others'."""
        self._full = Overflow("graph entries", MAX_GRAPH_ENTRIES, log=log)
        self._malformed = LogOnce(log)
        # A dropped token is undeclared: keep each until it is withdrawn.
        self._tokens: dict[str, zenoh.LivelinessToken] = {}
        self.watchers: CallbackList[[]] = CallbackList()
        self._topic_watchers: dict[str, CallbackList[[]]] = {}
        """Watchers of one topic each (this process's own, so bounded by what it declares)."""
        self._by_topic: dict[str, dict[str, GraphEntry]] = {}
        """``_entries`` by topic: a topic's read costs its entries, not the fleet's."""
        self._snapshot: frozenset[GraphEntry] | None = None
        """``_entries`` as ``entries()`` last returned them, until they change: a fleet's graph
        is read every round and changes far less often."""
        self._count = 0
        self._published: Counter[str] = Counter()
        """Publisher entries per topic: the channels live now."""

    def _add_locked(self, key: str, entry: GraphEntry) -> None:
        self._snapshot = None
        self._entries[key] = entry
        self._by_topic.setdefault(entry.topic, {})[key] = entry
        if entry.role is Role.PUBLISHER:
            self._published[entry.topic] += 1

    def _remove_locked(self, key: str) -> GraphEntry | None:
        entry = self._entries.pop(key, None)
        if entry is None:
            return None
        self._snapshot = None
        of_topic = self._by_topic[entry.topic]
        del of_topic[key]
        if not of_topic:
            del self._by_topic[entry.topic]
        if entry.role is Role.PUBLISHER:
            self._published[entry.topic] -= 1
            if self._published[entry.topic] <= 0:
                del self._published[entry.topic]
        return entry

    def _fire(self, topic: str) -> None:
        """Tell the graph's watchers, and ``topic``'s, that the entries changed."""
        self.watchers.fire()
        with self._lock:
            callbacks = self._topic_watchers.get(topic)
        if callbacks is not None:
            callbacks.fire()

    def keeps(self, name: str) -> bool:
        """Whether a full store keeps parameter ``name``: a global, or a live channel's."""
        split = split_channel_name(name)
        if split is None:
            return True
        with self._lock:
            return split[0] in self._published

    def follow(self, topic: str) -> None:
        """Hear ``topic``'s tokens from now on (and those already declared), if not yet.

        A publisher needs none: what others hold of its channel it fetches from the sessions
        that follow everything when it meets them and when it first writes there.
        """
        if self._follow_all:
            return
        with self._lock:
            if topic in self._followed:
                return
            self._followed.add(topic)
        self._transport.hold(
            lambda session: session.liveliness().declare_subscriber(
                keys.topic_graph_filter(topic), self.on_sample, history=True
            )
        )

    def announce(self, role: Role, topic: str, variant: Variant) -> Handle:
        check_topic(topic)
        transport = self._transport
        with self._lock:
            self._count += 1
            uid = f"{transport.node_id}.{self._count}"
        key = keys.graph_key(role.value, transport.host, uid, variant.value, topic)
        entry = GraphEntry(role, transport.host, topic, variant, uid)
        token = transport.session.liveliness().declare_token(key)
        with self._lock:
            self._add_locked(key, entry)
            self._tokens[key] = token
        self._fire(topic)

        def withdraw() -> None:
            with self._lock:
                self._remove_locked(key)
                self._tokens.pop(key, None)
                self._full.room(len(self._entries))
            _undeclare(token)
            self._fire(topic)

        return Closer(withdraw)

    def entries(self, *, topic: str | None = None) -> frozenset[GraphEntry]:
        if topic is not None:
            self.follow(topic)
        with self._lock:
            if topic is None:
                if self._snapshot is None:
                    self._snapshot = frozenset(self._entries.values())
                return self._snapshot
            return frozenset(self._by_topic.get(topic, {}).values())

    def watch(self, callback: Callable[[], None], *, topic: str | None = None) -> Handle:
        if topic is None:
            return self.watchers.add(callback)
        with self._lock:
            callbacks = self._topic_watchers.setdefault(topic, CallbackList())
        handle = callbacks.add(callback)
        self.follow(topic)
        return handle

    def on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        fields = keys.parse_graph_key(key)
        try:
            if fields is None or not keys.is_host_name(fields.host):
                raise ValueError(key)
            entry = GraphEntry(
                Role(fields.role), fields.host, fields.topic, Variant(fields.variant), fields.uid
            )
        except ValueError:
            self._malformed.warning(key, "ignoring malformed graph token %s", key)
            return
        with self._lock:
            if sample.kind == zenoh.SampleKind.PUT:
                if key in self._entries:
                    return
                if len(self._entries) >= MAX_GRAPH_ENTRIES:
                    self._full.refuse()
                    return
                self._add_locked(key, entry)
            elif self._remove_locked(key) is None:
                return
            else:
                self._full.room(len(self._entries))
        if sample.kind == zenoh.SampleKind.PUT:
            # A publisher declares its parameters before it announces itself: what its session
            # owns now includes them, even if their writes went out before they could reach us.
            self._transport.fetch_owner_of(entry.uid, entry.topic)
        self._fire(entry.topic)


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
        self.node_id = keys.new_node_id()
        connect, listen = tuple(connect), tuple(listen)
        if port is None:
            port = int(os.environ.get("DBML_ZENOH_PORT", DEFAULT_PORT))
        config = _config(
            connect=connect,
            listen=listen,
            config_file=config_file,
            shared_memory=shared_memory,
            port=port,
            host=self.host,
            priority_links=priority_links,
        )
        prepare_runtime()
        try:
            self.session: zenoh.Session = zenoh.open(config)
        except zenoh.ZError as err:
            raise TransportError(f"zenoh: cannot open a session: {err}") from err
        self._closed = False
        self._lock = threading.Lock()
        # Each declaration until it is closed: a dropped zenoh object is undeclared.
        self._declared: set[_Declaration] = set()
        self._sync = ParamSync(
            self.session,
            self.node_id,
            host=self.host,
            follow_all=follow_all_params,
            priority=_CONTROL,
            mesh_sessions=None if connect or listen or config_file else PEER_MESH_SESSIONS,
        )
        self.params = self._sync.params
        self.graph = _ZenohGraph(self, follow_all=follow_all_params)
        # A full store gives up a flood's names first: those of channels nobody publishes.
        self.params.keep = self.graph.keeps
        if follow_all_params:
            self._sync.hold(
                lambda session: session.liveliness().declare_subscriber(
                    f"{keys.GRAPH}/**", self.graph.on_sample, history=True
                )
            )
        _OPEN.add(self)

    # -- the parameter store ----------------------------------------------------------------

    def fetch_owner_of(self, uid: str, topic: str) -> None:
        """Fetch what the session that made graph entry ``uid`` on ``topic`` owns.

        Only if this session hears that channel's parameters.
        """
        self._sync.fetch_owner_of(uid, topic)

    def refresh(self, entry: GraphEntry) -> None:
        """Meet the session that made ``entry`` again: both fetch what the other owns."""
        self._sync.refresh(entry.uid)

    @property
    def control_messages_received(self) -> int:
        """Parameter writes and batches delivered to this session so far (for measurement)."""
        return self._sync.received_messages

    @property
    def control_bytes_received(self) -> int:
        """Their payloads' bytes so far (for measurement)."""
        return self._sync.received_bytes

    def param_stamp_ns(self, name: str) -> int | None:
        """When the newest write of ``name`` known here was made, in ns on its writer's clock.

        For measurement: on one host, its delay to this session. None if none is known.
        """
        stamped = self._sync.keyed.stamp(name)
        return None if stamped is None else stamped[0]

    def wait_for_peers(self, timeout_s: float) -> bool:
        """Wait until another dbml session is reachable and what the sessions met own is here.

        With ``follow_all_params=False``: a session that follows every parameter (an optimizer,
        a monitor), the only kind such a session meets.
        """
        return self._sync.wait_for_peers(timeout_s)

    def confirm_param(self, name: str, *, timeout_s: float) -> bool:
        """Whether another session holds our latest write of ``name`` (polled, bounded)."""
        return self._sync.confirm_param(name, timeout_s=timeout_s)

    # -- topics -------------------------------------------------------------------------------

    now = staticmethod(time.monotonic)
    """Monotonic seconds (the function itself: publishers read it per message)."""

    def hold(self, declare: Callable[[zenoh.Session], zenoh.Subscriber[None]]) -> None:
        """Make ``declare(session)`` and keep it until the transport closes (not if closing)."""
        self._sync.hold(declare)

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
        self._sync.close()
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
        # A session may open a link per range of priorities (``priority_links``) to it.
        config.insert_json5("transport/unicast/max_links", str(len(PRIORITY_LINK_RANGES)))
        put_link_timeouts(config)
        prepare_runtime(rx_threads=ROUTER_RX_THREADS, net_threads=NET_THREADS)
        return zenoh.open(config)
    except zenoh.ZError as err:
        raise TransportError(f"zenoh router: cannot listen on {endpoints!r}: {err}") from err
