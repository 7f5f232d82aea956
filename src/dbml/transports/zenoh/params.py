"""zenoh's half of the parameter store: meeting sessions, fetching what they own, confirming.

``KeyedParams`` (``dbml.transports.zenoh.keyed``: a ``Replica`` and its messages) knows no
session; this class wires it to one. Every session caches the writes it hears and serves what
it owns under its owned-values key (``dbml.protocol.keys``). Two sessions that meet (see each
other's node token, and again when their direct link comes up) each fetch what the other owns
and tell the other to fetch theirs, so what one wrote before the other could hear it is not
lost; after that, writes reach it. Two sessions that both follow only their own channels (two
robots) do not meet: such a session hears only the tokens of the sessions that follow
everything, and meets each. A session that does not
follow every parameter (a process that only publishes) hears the global ones, the batches for
every session and for its own host, and the channels it writes to.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from typing import TypeAlias

import zenoh

from dbml.core.errors import TransportError
from dbml.protocol import keys
from dbml.protocol.names import check_topic
from dbml.protocol.schema import GLOBAL_PREFIX
from dbml.transports.overflow import LogOnce, Overflow
from dbml.transports.replica import Replica
from dbml.transports.worker import FLUSH_TIMEOUT_S, BackgroundThread
from dbml.transports.zenoh.keyed import KeyedParams

__all__ = [
    "CONFIRM_POLL_S",
    "CONFIRM_QUERY_S",
    "LINK_POLL_S",
    "MAX_QUEUED_FETCHES",
    "MAX_SESSIONS",
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
MAX_SESSIONS = 4096
"""The most other dbml sessions a session keeps as met. A fleet of 160 robots, each with a
process per channel (4) and a few of its own, and the base station's, is under a thousand;
any peer can declare node tokens, so past this a new session is refused (not met, its values
not fetched; what it writes still arrives) and logged once per flood, with a count. A session
costs a few hundred bytes here: the bound is about a megabyte."""
MAX_QUEUED_FETCHES = 2 * MAX_SESSIONS
"""The most fetches and announcements waiting for the sync thread: one of each per session,
for every session at once (a newcomer meeting a full fleet). Each is queued once (a second
request for one already waiting is that one); past the bound a new request is refused and
logged once per flood (the optimizer asks again each period for what it misses). Any peer can
ask (a pull, a graph entry), hence the bound."""

_OWN_ANY = keys.own_key("*")
"""Any session's owned values."""
_HELD = "held"
"""The query parameter asking every session for the one value named, owned or not."""
_PULL = "pull"
"""The query parameter telling a session to fetch what the named session owns."""

_WRITE_CONGESTION = zenoh.CongestionControl.BLOCK
"""A parameter write waits for room on the way: it is said once."""
_BATCH_CONGESTION = zenoh.CongestionControl.DROP
"""A batch is dropped on the way to a session that reads late: the heartbeat goes every round."""

_Declared: TypeAlias = "zenoh.Subscriber[None] | zenoh.Queryable[None] | zenoh.LivelinessToken"


def _undeclare(declared: _Declared) -> None:
    with contextlib.suppress(zenoh.ZError):
        declared.undeclare()  # type: ignore[no-untyped-call]  # the stubs leave it unannotated


class ParamSync:
    """The parameter store of one zenoh session, identified by ``node_id``.

    ``params`` is the store; ``priority`` is the class of every control message (ahead of bulk
    data). ``follow_all=False`` hears only the global parameters, the batches for every session
    and for ``host``, and the channels this session writes to.
    """

    def __init__(
        self,
        session: zenoh.Session,
        node_id: str,
        *,
        host: str,
        follow_all: bool,
        priority: zenoh.Priority,
        mesh_sessions: int | None = None,
    ) -> None:
        self.session = session
        self._mesh_sessions = mesh_sessions
        """In zenoh's peer mesh: past this many sessions it is said once (else None)."""
        self._mesh_said = False
        self.node_id = node_id
        self._priority = priority
        self._closed = False
        self._lock = threading.Lock()
        self._declared: list[_Declared] = []
        self._peers = threading.Event()
        self._live: dict[str, str] = {}
        """The dbml sessions met and still alive: node id to zenoh id (``MAX_SESSIONS``)."""
        self._live_full = Overflow("dbml sessions met", MAX_SESSIONS, log=log)
        self._malformed = LogOnce(log)
        self._fetching = 0
        self._zids: dict[str, str] = {}
        """The live sessions' zenoh ids, to their node ids: one per live session at most."""
        self._linked: set[str] = set()
        """The zenoh ids this session has a direct link to, as last seen (zenoh bounds them)."""
        self._meet_again: dict[str, float] = {}
        """Live sessions to meet once more, and when: a subset of ``_live``."""
        self._synced = threading.Condition(self._lock)
        self._queued: OrderedDict[tuple[str, bool], None] = OrderedDict()
        """The sync thread's work, oldest first, each once: ``(node, False)`` fetches what
        ``node`` owns, ``(node, True)`` tells it to fetch ours (``MAX_QUEUED_FETCHES``)."""
        self._queued_full = Overflow("parameter fetches queued", MAX_QUEUED_FETCHES, log=log)
        self._work = threading.Condition(self._lock)
        self._replier = node_id.encode()
        self._counter_lock = threading.Lock()
        self._received = 0
        self._received_bytes = 0
        self._follow_all = follow_all
        self._follow_everything: set[str] = set()
        """The live sessions that follow every parameter (a subset of ``_live``)."""
        self._followed: set[str] = set()
        """The channels whose parameters this session hears, when it does not hear them all."""
        self.keyed = KeyedParams(node_id, send=self._send)
        self.params: Replica = self.keyed.replica
        self._thread = BackgroundThread(self._fetch_loop, name="dbml-param-sync", log=log).start()
        heard = f"{keys.PARAM}/**" if follow_all else keys.global_params_filter()
        batches = [f"{keys.BATCH}/**"] if follow_all else [keys.batch_key(), keys.batch_key(host)]
        self._declared += [
            session.declare_subscriber(heard, self._on_param),
            *(session.declare_subscriber(batch, self._on_batch) for batch in batches),
            session.declare_queryable(keys.own_key(node_id, "/**"), self._on_query),
            session.liveliness().declare_subscriber(
                keys.node_filter(follows_all=follow_all), self._on_node, history=True
            ),
            session.liveliness().declare_token(
                keys.node_key(node_id, str(session.info.zid()), follows_all=follow_all)
            ),
        ]

    def _send(self, key: str, data: bytes) -> None:
        """Put one parameter write or batch (on the store's sender thread, never a callback's).

        Control traffic, sent ahead of bulk data. A write waits for room rather than be dropped.
        A batch (the optimizer's round) does not: a router routes a sender's messages in order,
        and one reliable message to a session that reads late holds the rest there, for every
        robot. The heartbeat goes every round and a rate not acknowledged is pushed again a period
        later; a status or ``managed`` flag (said only when it changes) stays stale there.
        A session that does not hear every parameter starts hearing a channel's when it first
        writes one of them (a publisher's bounds): others' writes there are its business.
        """
        if not self._follow_all:
            self._follow(key)
        self.session.put(
            key,
            data,
            congestion_control=_BATCH_CONGESTION
            if key.startswith(keys.BATCH)
            else _WRITE_CONGESTION,
            priority=self._priority,
        )

    def hold(self, declare: Callable[[zenoh.Session], _Declared]) -> _Declared | None:
        """Make ``declare(session)`` and keep it until this store closes (None: closing)."""
        with self._lock:
            if self._closed:
                return None
        try:
            declaration = declare(self.session)
        except zenoh.ZError:
            return None  # closing: nothing left to declare
        with self._lock:
            closed = self._closed
            if not closed:
                self._declared.append(declaration)
        if closed:  # closed meanwhile: undeclared here, outside the lock (a middleware call)
            _undeclare(declaration)
            return None
        return declaration

    def _follow(self, key: str) -> None:
        """Hear the parameters of the channel that ``key`` (a parameter write's) belongs to."""
        channel = keys.channel_params_filter(key)
        if channel is None:  # a global parameter (heard already), or not a channel's
            return
        with self._lock:
            if channel in self._followed or self._closed:
                return
            self._followed.add(channel)
        if self.hold(lambda session: session.declare_subscriber(channel, self._on_param)) is None:
            return  # closing: nothing left to hear
        # What others wrote there between the meetings' fetches and now, from its owners: the
        # sessions that follow everything (a robot owns nothing of another's channel). Asking
        # every session instead cost a fleet of 80 x 4 26,000 queries at its start.
        with self._lock:
            owners = sorted(self._follow_everything)
        for node in owners:
            self.session.get(
                f"{keys.own_key(node)}/{channel[len(keys.PARAM) + 1 :]}",
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
        if owned is not None and keys.is_node_id(owned[0]):
            self.keyed.on_value(owned[1], sample.payload.to_bytes())

    def _on_param(self, sample: zenoh.Sample) -> None:
        payload = sample.payload.to_bytes()
        self._count_received(len(payload))
        self.keyed.on_write(str(sample.key_expr), payload)

    def _on_batch(self, sample: zenoh.Sample) -> None:
        payload = sample.payload.to_bytes()
        self._count_received(len(payload))
        self.keyed.on_batch(payload)

    def _count_received(self, size_bytes: int) -> None:
        with self._counter_lock:
            self._received += 1
            self._received_bytes += size_bytes

    @property
    def received_messages(self) -> int:
        """Parameter writes and batches delivered to this session so far (what it paid for)."""
        with self._counter_lock:
            return self._received

    @property
    def received_bytes(self) -> int:
        """Their payloads' bytes so far."""
        with self._counter_lock:
            return self._received_bytes

    @property
    def alive(self) -> bool:
        """False once the sync thread or the store's sender thread died."""
        return self._thread.alive and self.params.alive

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
            data = self.keyed.held(name) if name else None
            if data is not None:
                query.reply(own + name, data, attachment=self._replier)
            return
        puller = parameters.get(_PULL)
        if puller is not None:
            self._schedule_fetch(puller)
            return
        asked = query.key_expr
        for name, data in self.keyed.owned(self._is_live, prefix=_name_prefix(str(asked), own)):
            reply_key = own + name
            if asked.intersects(reply_key):
                query.reply(reply_key, data, attachment=self._replier)

    def _on_node(self, sample: zenoh.Sample) -> None:
        parsed = keys.parse_node_key(str(sample.key_expr))
        if parsed is None or not keys.is_node_id(parsed[0]):
            log.warning("ignoring malformed session token %s", str(sample.key_expr)[:80])
            return
        node, zid, follows_all = parsed
        if node == self.node_id:
            return
        with self._lock:
            if sample.kind != zenoh.SampleKind.PUT:
                self._follow_everything.discard(node)
                met_as = self._live.pop(node, None)
                if met_as is not None and self._zids.get(met_as) == node:
                    del self._zids[met_as]
                self._meet_again.pop(node, None)
                self._live_full.room(len(self._live))
                return
            if node in self._live:
                return
            if len(self._live) >= MAX_SESSIONS:
                self._live_full.refuse()
                return
            self._live[node] = zid
            if follows_all:
                self._follow_everything.add(node)
            apart = not (self._follow_all or follows_all)  # not heard: ``keys.node_filter``
            if not apart:
                self._zids[zid] = node
            sessions = len(self._live) + 1
            crowded = (
                self._mesh_sessions is not None
                and sessions > self._mesh_sessions
                and not self._mesh_said
            )
            self._mesh_said |= crowded
        if crowded:
            log.warning(
                "%d dbml sessions in zenoh's peer mesh (no --connect): past %d it did not "
                "complete on a 2-core machine, and peers send only over direct links; run "
                "`dbml router` and give every process --connect tcp/ROUTER:7447 "
                "(docs/benchmarks.md)",
                sessions,
                self._mesh_sessions,
            )
        self._peers.set()
        if not apart:  # two sessions that follow only their own hold nothing for each other
            self._meet(node)

    def _meet(self, node: str, *, again: bool = True) -> None:
        """Tell ``node`` to fetch what we own and fetch what it owns (off zenoh's thread).

        What we wrote before our writes could reach its subscriber is in that fetch; from then
        on our writes reach it. But a session's token can arrive before its subscriber's
        declaration (or, from a peer's answer, before the link to it is up), so the meeting is
        repeated once ``MEET_AGAIN_S`` later, and whenever a direct link to it comes up. A
        meeting goes both ways, so one side's repeat does for both: the side that follows
        everything repeats it (a robot meets only such sessions). At 80 x 4 the robots'
        repeats were about a third of their queries at the fleet's start, each routed by the
        router under one lock.
        """
        with self._lock:
            self._queue_locked(node, announce=True)
            if again and self._follow_all and node in self._live:  # once, the latest meeting's
                self._meet_again[node] = time.monotonic() + MEET_AGAIN_S
        self._schedule_fetch(node)

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
            due = [node for node, at in self._meet_again.items() if at <= now]
            for node in due:
                del self._meet_again[node]
        for node in fresh:
            self._meet(node)
        for node in due:
            self._meet(node, again=False)

    def fetch_owner_of(self, uid: str, topic: str) -> None:
        """Fetch what the session that made graph entry ``uid`` (``<node id>.<n>``) owns.

        Only if this session hears the parameters of ``topic``: a robot has no use for another
        robot's (80 robots fetching each other's on every declaration was a fleet's start).
        """
        node = uid.partition(".")[0]
        if node == self.node_id:
            return
        if not self._follow_all:
            with self._lock:
                if keys.topic_params_filter(topic) not in self._followed:
                    return
        self._schedule_fetch(node)

    def refresh(self, uid: str) -> None:
        """Meet the session that made graph entry ``uid`` again: both fetch what the other owns."""
        node = uid.partition(".")[0]
        if node != self.node_id and keys.is_node_id(node):
            self._meet(node, again=False)

    def _schedule_fetch(self, node: str) -> None:
        """Fetch ``node``'s values soon, once: a fetch already waiting covers this one too."""
        if not keys.is_node_id(node):
            self._malformed.warning(
                node, "ignoring a fetch request from a malformed node id %s", node[:40]
            )
            return
        with self._lock:
            if self._queue_locked(node, announce=False):
                self._fetching += 1

    def _queue_locked(self, node: str, *, announce: bool) -> bool:
        """Queue work for the sync thread, unless the same is queued or the queue is full.

        True when queued anew (under the lock).
        """
        item = (node, announce)
        if item in self._queued:
            return False
        if len(self._queued) >= MAX_QUEUED_FETCHES:
            self._queued_full.refuse()
            return False
        self._queued[item] = None
        self._work.notify_all()
        return True

    def _next(self) -> tuple[str, bool] | None:
        """The oldest work queued, waiting for some up to ``LINK_POLL_S``; None if there is none."""
        with self._lock:
            if not self._work.wait_for(
                lambda: bool(self._queued) or self._closed, timeout=LINK_POLL_S
            ):
                return None
            if self._closed:
                return None
            item, _ = self._queued.popitem(last=False)
            self._queued_full.room(len(self._queued))
            return item

    def _fetch_loop(self) -> None:
        """Ask sessions for their values, or to ask for ours; answers arrive on zenoh's threads.

        A failure is logged and the loop goes on: a dead loop would leave this session deaf to
        every value written before it could hear it. Should it end all the same (something
        other than an ``Exception``), its death is logged and ``alive`` turns False.
        """
        while not self._closed:
            try:
                self._new_links()
                item = self._next()
                if item is not None:
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

        def on_reply(reply: zenoh.Reply) -> None:
            sample = reply.ok
            if sample is None:
                return
            key = str(sample.key_expr)
            if key.startswith(prefix + "/"):
                self.keyed.on_value(key[len(prefix) :], sample.payload.to_bytes())

        selectors = self._fetched_selectors(prefix)
        left = [len(selectors)]

        def done() -> None:
            with self._counter_lock:
                left[0] -= 1
                last = left[0] == 0
            if last:
                self._fetched()

        asked = 0
        try:
            for selector in selectors:
                self.session.get(
                    selector,
                    zenoh.handlers.Callback(on_reply, done),
                    target=zenoh.QueryTarget.ALL,
                    consolidation=zenoh.ConsolidationMode.NONE,
                    timeout=SYNC_TIMEOUT_S,
                    priority=self._priority,
                )
                asked += 1
        except BaseException:
            for _ in range(len(selectors) - asked):
                done()
            raise

    def _fetched_selectors(self, prefix: str) -> list[str]:
        """What to fetch of a session's values (``prefix``: its owned-values key).

        Everything, for a session that follows everything; else the global values and the
        channels this one hears. The optimizer owns every channel's rate: a robot that fetched
        all it owns took 700 answers at 80 x 4, and 80 robots at once filled its queue for 5 s.
        """
        if self._follow_all:
            return [f"{prefix}/**"]
        with self._lock:
            followed = sorted(self._followed)
        channels = [f"{prefix}/{channel[len(keys.PARAM) + 1 :]}" for channel in followed]
        return [f"{prefix}{GLOBAL_PREFIX}/**", *channels]

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
        mine = self.keyed.stamp(name)
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
            self._fetching -= sum(1 for _, announce in self._queued if not announce)
            self._queued.clear()
            self._work.notify_all()
            self._synced.notify_all()
        if not self.params.close():
            log.warning("closing with parameter writes unsent after %.1f s", FLUSH_TIMEOUT_S)
        for item in declared:
            _undeclare(item)


def _name_prefix(selector: str, own: str) -> str:
    """What every name a query on ``own`` (this session's owned-values key) selects starts with.

    The literal part of its key expression after ``own``, up to the chunk with the first
    wildcard (``own`` + ``/r1/ch0/**``: ``/r1/ch0``); empty when it does not name ``own``
    literally. A prefix, not a match: the key expression still decides.
    """
    rest = selector[len(own) :]
    if not selector.startswith(own) or not rest.startswith("/"):
        return ""  # another session's key, all of this one's, or its key as a pattern
    wild = min((i for i in (rest.find("*"), rest.find("$")) if i >= 0), default=len(rest))
    return rest[: rest.rfind("/", 0, wild)] if wild < len(rest) else rest
