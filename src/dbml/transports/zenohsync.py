"""zenoh's half of the parameter store: meeting sessions, fetching what they own, confirming.

``ReplicatedParams`` (``dbml.transports.paramstore``) holds the values and knows no middleware;
this class wires it to a zenoh session. Every session caches the writes it hears and serves what
it owns under its owned-values key (``dbml.protocol.keys``). Two sessions that meet (see each
other's node token, and again when their direct link comes up) each fetch what the other owns
and tell the other to fetch theirs, so what one wrote before the other could hear it is not
lost; after that, writes reach it. A session that does not follow every parameter (a process
that only publishes) hears the global ones, the batches and the channels it writes to.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import re
import threading
import time
from typing import TypeAlias

import zenoh

from dbml.core.errors import TransportError
from dbml.protocol import keys
from dbml.protocol.names import check_topic
from dbml.transports.paramstore import ReplicatedParams

__all__ = [
    "CONFIRM_POLL_S",
    "CONFIRM_QUERY_S",
    "LINK_POLL_S",
    "MEET_AGAIN_S",
    "SYNC_TIMEOUT_S",
    "ParamSync",
]

log = logging.getLogger("dbml.zenoh")

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

_OWN_ANY = keys.own_key("*")
"""Any session's owned values."""
_HELD = "held"
"""The query parameter asking every session for the one value named, owned or not."""
_PULL = "pull"
"""The query parameter telling a session to fetch what the named session owns."""
_NODE_ID = re.compile(r"[0-9a-f]{16}")
"""A session's node id: 16 hex digits of a random UUID."""

_Declared: TypeAlias = "zenoh.Subscriber[None] | zenoh.Queryable[None] | zenoh.LivelinessToken"


def _undeclare(declared: _Declared) -> None:
    with contextlib.suppress(zenoh.ZError):
        declared.undeclare()  # type: ignore[no-untyped-call]  # the stubs leave it unannotated


class ParamSync:
    """The parameter store of one zenoh session, identified by ``node_id``.

    ``params`` is the store; ``priority`` is the class of every control message (ahead of bulk
    data). ``follow_all=False`` hears only the global parameters, the batches and the channels
    this session writes to.
    """

    def __init__(
        self,
        session: zenoh.Session,
        node_id: str,
        *,
        follow_all: bool,
        priority: zenoh.Priority,
    ) -> None:
        self.session = session
        self.node_id = node_id
        self._priority = priority
        self._closed = False
        self._lock = threading.Lock()
        self._declared: list[_Declared] = []
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
        self._replier = node_id.encode()
        self._follow_all = follow_all
        self._followed: set[str] = set()
        """The channels whose parameters this session hears, when it does not hear them all."""
        self.params = ReplicatedParams(node_id, send=self._send)
        threading.Thread(target=self._fetch_loop, name="dbml-param-sync", daemon=True).start()
        heard = f"{keys.PARAM}/**" if follow_all else keys.global_params_filter()
        self._declared += [
            session.declare_subscriber(heard, self._on_param),
            session.declare_subscriber(keys.BATCH, self._on_batch),
            session.declare_queryable(keys.own_key(node_id, "/**"), self._on_query),
            session.liveliness().declare_subscriber(f"{keys.NODE}/**", self._on_node, history=True),
            session.liveliness().declare_token(keys.node_key(node_id, str(session.info.zid()))),
        ]

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
            priority=self._priority,
        )

    def _follow(self, key: str) -> None:
        """Hear the parameters of the channel that ``key`` (a parameter write's) belongs to."""
        channel = keys.channel_params_filter(key)
        if channel is None:  # a global parameter (heard already), or not a channel's
            return
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
            self._declared.append(subscriber)
        # What others wrote there between the meetings' fetches and now, from its owners.
        own = f"{_OWN_ANY}/{channel[len(keys.PARAM) + 1 :]}"
        self.session.get(
            own,
            zenoh.handlers.Callback(self._on_owned_reply, lambda: None),
            target=zenoh.QueryTarget.ALL,
            consolidation=zenoh.ConsolidationMode.NONE,
            timeout=SYNC_TIMEOUT_S,
            priority=self._priority,
        )

    def _on_owned_reply(self, reply: zenoh.Reply) -> None:
        """A value some session owns, from its owned-values key."""
        sample = reply.ok
        if sample is None:
            return
        owned = keys.own_name(str(sample.key_expr))
        if owned is not None and _NODE_ID.fullmatch(owned[0]):
            self.params.on_value(owned[1], sample.payload.to_bytes())

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
        own = keys.own_key(self.node_id)
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
        parsed = keys.parse_node_key(str(sample.key_expr))
        if parsed is None:
            log.warning("ignoring malformed session token %s", str(sample.key_expr)[:80])
            return
        node, zid = parsed
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

    def refresh(self, uid: str) -> None:
        """Meet the session that made graph entry ``uid`` again: both fetch what the other owns."""
        node = uid.partition(".")[0]
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
        prefix = keys.own_key(node)
        if announce:
            self.session.get(
                f"{prefix}?{_PULL}={self.node_id}", lambda _reply: None, priority=self._priority
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
                priority=self._priority,
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
                    _, stamp, writer = keys.decode_param(sample.payload.to_bytes())
                except TransportError:
                    continue
                if (stamp, writer) == mine:
                    return True
            time.sleep(min(CONFIRM_POLL_S, max(0.0, deadline - time.monotonic())))
        return False

    def close(self) -> None:
        """Send the queued writes (bounded), stop the sync thread, undeclare what it declared."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            declared, self._declared = self._declared, []
        self.params.close()
        self._fetches.put(None)
        for item in declared:
            _undeclare(item)
