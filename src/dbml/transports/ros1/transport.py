"""The ROS 1 transport: real ROS topics, the ROS parameter server and the master's graph.

- Topics: ``[topic]`` and ``[topic]/optimized`` are ordinary ROS topics of the message class
  registered for the topic (``use_message_class``). A payload is the serialised message: it is
  sent as it is (no second serialisation) and received raw, so its length is the serialised
  size. Topics without a class (dbml's own JSON reports) travel as ``std_msgs/String``.
- Parameters: the real parameter server, under the paper's absolute names, so ``rosparam get``
  and ``rosparam set`` work on them. The master pushes every change (``subscribeParam``, then
  ``paramUpdate`` calls) to a small XML-RPC endpoint of this process; reads are served from that
  mirror, so nothing polls the master per message. Writes go to the master from a sender thread
  (a write may come from inside the master's own push): ``set`` never blocks.
- Graph: the master's ``getSystemState``; each node's host is the host of its URI, which
  ``ROS_IP`` / ``ROS_HOSTNAME`` decide. It is refreshed only while someone watches it, and nodes
  that no longer answer (killed without unregistering) are left out.
- No attachments: ROS 1 messages carry none, so subscribers see ``attachment=None`` (no
  per-message latency or loss, hence no bandwidth estimation over ROS 1).

rospy allows one node per process, so there is one ``Ros1Transport`` per process
(``Ros1Transport.shared()`` opens it on first use); it reuses a node the application already
started with ``rospy.init_node``.
"""

from __future__ import annotations

import atexit
import io
import logging
import os
import struct
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, Final, TypeAlias
from urllib.parse import urlparse
from xmlrpc.server import SimpleXMLRPCServer

from dbml.core.errors import TransportError
from dbml.transports.base import (
    Closer,
    GraphEntry,
    Handle,
    ParamValue,
    Role,
    Sample,
    TransportBase,
    TransportPriority,
    Variant,
    check_param_value,
    check_topic,
    resolve_host,
)
from dbml.transports.callbacks import CallbackList
from dbml.transports.overflow import Overflow
from dbml.transports.paramstore import MAX_PARAMS
from dbml.transports.ros1.master import CALL_TIMEOUT_S, ROSPY_MISSING, MasterClient
from dbml.transports.worker import (
    DEFAULT_SENDER_CAPACITY,
    FLUSH_TIMEOUT_S,
    BackgroundThread,
    OrderedSender,
    PeriodicWorker,
)

try:
    import rosgraph.network
    import rospy
    import std_msgs.msg
except ImportError as err:  # pragma: no cover - depends on the machine
    raise ImportError(ROSPY_MISSING) from err

__all__ = ["Ros1Transport", "serialize"]

log = logging.getLogger("dbml.ros1")

GRAPH_POLL_S = 0.25
"""How often a watched graph is re-read from the master (one ``getSystemState`` call)."""
LIVENESS_S = 2.0
"""How long a node's answer to ``getPid`` counts as alive."""
NODE_PING_TIMEOUT_S = 0.5
"""How long a node has to answer ``getPid`` before it counts as gone."""
RECEIVE_BUFFER_BYTES = 1 << 24
"""rospy's receive buffer per subscription: room for a few large camera frames."""
MAX_MIRRORED_PARAMS = MAX_PARAMS
"""The most parameter names mirrored from the parameter server: the zenoh store's bound, for the
same fleet. Anyone can write there, so past it a push of a new name is refused and logged once
per flood (names held are still updated and deleted); this process's own writes are always
taken (its code bounds them, and read-your-writes depends on them)."""
ECHO_WAIT_S = 5.0
"""How long this process's write of a name waits for its echo, the master's push of it back;
until then pushes of that name are older than it and skipped. Counted from the write while it is
queued, then from when it is handed to the master (its call lasts at most ``CALL_TIMEOUT_S``; a
live master pushes at once). Past it the echo is taken as lost: the master's pushes apply."""
MAX_AWAITED_ECHOES = 64
"""The most writes of one name handed to the master whose echoes are awaited: a live master
echoes within milliseconds, so there are a few. Past it the oldest is forgotten (its echo, when
it comes, is skipped as an older push): a name written fast while echoes are lost stays bounded."""
MAX_EARLY_PUSHES = 4096
"""The most pushes kept while the parameter subscription's call runs (they are newer than the
tree it returns, so they are applied after it). That call lasts at most ``CALL_TIMEOUT_S``, and
a fleet's writes in that time are a few per channel: 160 robots with 4 channels write a few
hundred. Anyone can call the push endpoint, so past this a push is not kept: the whole tree is
read again once the subscription is in (what the pushes said is in it), and the flood is
logged once, with a count."""
_OPTIMIZED = "/" + Variant.OPTIMIZED.value
_STRING = std_msgs.msg.String
_SCALARS = (bool, int, float, str)
_FRAME_PREFIX_BYTES = 4
"""A ``std_msgs/String`` starts with its length (uint32)."""
_OK: Final = [1, "", 0]
"""An XML-RPC API's success: code, message, value."""


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


def _flatten(name: str, value: object, out: dict[str, ParamValue]) -> None:
    """Parameter-server values as leaves: ``{'dbm': {'x': 1}}`` at ``/`` is ``/dbm/x = 1``."""
    if isinstance(value, dict):
        for key, sub in value.items():
            _flatten(f"{name.rstrip('/')}/{key}", sub, out)
    elif isinstance(value, _SCALARS):
        out[name] = value  # lists and binary values are not dbml parameters


def _use_host(host: str) -> None:
    """Make this process's ROS node take ``host`` as its address, before the node starts.

    rosgraph reads the override on every use (the node's URI, each topic connection's address,
    the bind address), from ``__hostname:=`` on the command line first, then ``ROS_HOSTNAME`` /
    ``ROS_IP``. There is no per-node setting, so it goes where it stays inside this process: the
    command line's ROS remapping (first, so it wins), not the environment, which every child
    process would inherit.
    """
    sys.argv.insert(1, f"__hostname:={resolve_host(host)}")


def _typed(value: ParamValue) -> tuple[type, ParamValue]:
    """A value with its type, so ``True`` and ``1`` compare as different writes."""
    return type(value), value


def _under(name: str, namespace: str) -> bool:
    return namespace in {"/", name} or name.startswith(namespace + "/")


_Write: TypeAlias = tuple[str, ParamValue]
"""A write queued for the master: name and value (None deletes)."""


@dataclass(slots=True)
class _Awaited:
    """This process's writes of one name whose echo (the master's push of it) has not come."""

    queued: _Write | None = None
    """The newest write, not handed to the master yet: every push of the name is older."""
    queued_until: float = 0.0
    """When a write still queued stops holding pushes back (dropped by a full queue, or stalled)."""
    sent: deque[tuple[ParamValue, float]] = field(default_factory=deque)
    """Values handed to the master, oldest first (their echoes come in this order), each with
    when its echo counts as lost; at most ``MAX_AWAITED_ECHOES``."""


class _Ros1Params:
    """The parameter server, mirrored in this process from the master's pushes.

    ``set`` applies a write to the mirror and tells this process's watchers at once, then
    queues it for the master: it never blocks, also on the push endpoint's thread or with the
    master stalled. The master pushes every write back, ours too, in the order it took them: so
    until the echo of this process's newest write of a name comes, a push of that name is older
    (an echo of our earlier write, or another's that ours overwrote) and is skipped, never taking
    the mirror back; the echo itself is no change. An echo not back within ``ECHO_WAIT_S`` is
    taken as lost, and pushes apply again.

    At most ``MAX_MIRRORED_PARAMS`` names are mirrored: past it a push of a new name is refused
    (logged once per flood); this process's own writes are always taken.
    """

    def __init__(
        self,
        master: MasterClient,
        node_name: str,
        host: str,
        bind: str,
        *,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._master = master
        self._clock = clock
        self._lock = threading.Lock()
        self._mirror: dict[str, ParamValue] = {}
        """Every name's value: up to ``MAX_MIRRORED_PARAMS`` from pushes, and our writes."""
        self._full = Overflow("parameter names mirrored", MAX_MIRRORED_PARAMS, log=log)
        self._own: dict[str, _Awaited] = {}
        """Our writes whose echo has not come, by name (bounded by the names we write)."""
        self._watchers: CallbackList[[str, ParamValue]] = CallbackList()
        # Pushes that arrive while the subscription call runs, applied after the tree it returns.
        self._early: list[tuple[str, object]] | None = []
        self._early_dropped = 0
        """Pushes not kept in ``_early``, which was full (``MAX_EARLY_PUSHES``)."""
        self._server = SimpleXMLRPCServer((bind, 0), logRequests=False, allow_none=True)
        self._server.register_function(self._param_update, "paramUpdate")  # type: ignore[arg-type]
        self._server.register_function(lambda _caller: [1, "", os.getpid()], "getPid")
        self._server.register_function(lambda _caller, _msg="": _OK, "shutdown")
        port = self._server.server_address[1]
        self._api = f"http://{host}:{port}/"
        # A caller id of its own: the master would shut down a node re-registered at another URI.
        self._subscriber = MasterClient(master.uri, caller_id=f"{node_name}/dbml_params")
        self._thread = BackgroundThread(
            self._server.serve_forever, name="dbml-ros1-params", log=log
        ).start()
        self._sender: OrderedSender[_Write] = OrderedSender(
            self._write,
            name="dbml-ros1-param-send",
            log=log,
            capacity=DEFAULT_SENDER_CAPACITY,  # one per name: a fleet optimizer's, many times
            describe=lambda item: f"parameter write {item[0]}",
            on_exit=master.close,  # the sender thread's own connection
        )
        try:
            tree = self._subscriber.call("subscribeParam", self._api, "/")
        except TransportError:
            self._sender.close(0)
            self._stop_server()
            raise
        changes: list[tuple[str, ParamValue]] = []
        with self._lock:
            self._apply("/", tree)  # the first values: nobody watches yet
            for pushed_key, pushed_value in self._early or []:
                changes += self._apply(pushed_key, pushed_value)
            self._early = None
        self._notify(changes)
        if self._early_dropped:
            self._reread()

    def _reread(self) -> None:
        """Pushes were dropped while subscribing: read the whole tree again and apply it.

        Pushes that arrive meanwhile are newer than the tree read: kept and applied after it,
        as at the subscription (once: a flood that outlasts it is not chased).
        """
        with self._lock:
            dropped, self._early_dropped = self._early_dropped, 0
            self._early = []
        log.warning(
            "%d parameter pushes arrived while subscribing, more than the %d kept: reading "
            "every parameter again",
            MAX_EARLY_PUSHES + dropped,
            MAX_EARLY_PUSHES,
        )
        try:
            tree: object = self._subscriber.call("getParam", "/")
        except TransportError as err:
            log.warning("reading the parameters again failed: %s", err)
            tree = None
        changes: list[tuple[str, ParamValue]] = []
        with self._lock:
            if tree is not None:
                changes += self._apply("/", tree)
            for pushed_key, pushed_value in self._early or []:
                changes += self._apply(pushed_key, pushed_value)
            self._early = None
            dropped, self._early_dropped = self._early_dropped, 0
        self._notify(changes)
        if dropped:
            log.warning("%d more parameter pushes were not kept while reading again", dropped)

    def _param_update(self, _caller: str, key: str, value: object) -> list[object]:
        """The master's push: a key (with a trailing ``/``) and its new value; ``{}`` deletes."""
        with self._lock:
            if self._early is not None:  # newer than the subscription's tree, which is not in yet
                if len(self._early) < MAX_EARLY_PUSHES:
                    self._early.append((key, value))
                else:
                    self._early_dropped += 1  # read again whole once subscribed
                return _OK
            changes = self._apply(key, value)
        self._notify(changes)
        return _OK

    def _apply(self, key: str, value: object) -> list[tuple[str, ParamValue]]:
        """Update the mirror (under the lock) from one push; the changes, deletions first.

        A value the mirror holds already (the echo of this process's newest write) is no change:
        its watchers heard it when it was set. Names of our writes still awaiting their echo are
        left as they are (``_awaiting_echo``); a new name past ``MAX_MIRRORED_PARAMS`` is refused.
        """
        namespace = key.rstrip("/") or "/"
        fresh: dict[str, ParamValue] = {}
        _flatten(namespace, value, fresh)
        awaiting = self._awaiting_echo(namespace, fresh)
        gone = [
            k for k in self._mirror if _under(k, namespace) and k not in fresh and k not in awaiting
        ]
        for name in gone:
            del self._mirror[name]
        changed: list[tuple[str, ParamValue]] = []
        refused = 0
        for name, new in fresh.items():
            if name in awaiting:
                continue
            if name in self._mirror:
                if _typed(self._mirror[name]) == _typed(new):
                    continue
            elif len(self._mirror) >= self._full.bound:
                refused += 1
                continue
            self._mirror[name] = new
            changed.append((name, new))
        if refused:
            self._full.refuse(refused)
        self._full.room(len(self._mirror))
        return [(name, None) for name in gone] + changed

    def _awaiting_echo(self, namespace: str, fresh: Mapping[str, ParamValue]) -> set[str]:
        """The names under a push's ``namespace`` whose push is older than our write of them.

        The master pushes in the order it took the writes: until the echo of our newest write of
        a name, a push of that name was taken before it. Our writes' echoes (our values, pushed
        at that very name, in the order sent) are counted off; the newest one's ends the wait,
        and so does ``ECHO_WAIT_S``: the push then applies as any other (no change, for an echo).
        """
        if not self._own:
            return set()
        now = self._clock()
        awaiting: set[str] = set()
        for name in [n for n in self._own if _under(n, namespace)]:
            own = self._own[name]
            if own.queued is not None and now >= own.queued_until:
                own.queued = None
            while own.sent and now >= own.sent[0][1]:
                own.sent.popleft()  # lost
            if (
                own.sent
                and name == namespace
                and fresh.keys() <= {name}  # a value or a deletion at the name, as we write
                and _typed(fresh.get(name)) == _typed(own.sent[0][0])
            ):
                own.sent.popleft()  # the echo of our oldest write sent
            if own.sent or own.queued is not None:
                awaiting.add(name)
            else:
                del self._own[name]
        return awaiting

    def _notify(self, changes: list[tuple[str, ParamValue]]) -> None:
        for name, value in changes:
            self._watchers.fire(name, value)

    def set(self, name: str, value: ParamValue) -> None:
        """Write here and notify at once; the sender thread writes it on the parameter server."""
        check_param_value(value)
        check_topic(name)
        write: _Write = (name, value)
        with self._lock:  # read-your-writes before the master has it
            if value is None:
                self._mirror.pop(name, None)
            else:
                self._mirror[name] = value
            own = self._own.setdefault(name, _Awaited())
            own.queued, own.queued_until = write, self._clock() + ECHO_WAIT_S
            # Queued under the lock, so the master gets a name's writes in the mirror's order;
            # a newer one replaces its older one still queued.
            self._sender.put(write, slot=name)
        self._full.room(len(self._mirror))
        self._watchers.fire(name, value)

    def _write(self, write: _Write) -> None:
        """One write on the parameter server (on the sender thread)."""
        name, value = write
        awaited = (value, self._clock() + ECHO_WAIT_S)
        with self._lock:
            own = self._own.setdefault(name, _Awaited())  # gone if it waited past ECHO_WAIT_S
            if own.queued is write:
                own.queued = None
            if len(own.sent) >= MAX_AWAITED_ECHOES:
                own.sent.popleft()
            own.sent.append(awaited)
        echoed = False
        try:
            if value is None:  # deleting a name the master lacks changes nothing: no push
                echoed = self._master.call("deleteParam", name, missing_ok=True) is not None
            else:
                echoed = self._master.call("setParam", name, value) is not None
        finally:
            if not echoed:  # failed, or nothing to push back: await no echo of it
                with self._lock:
                    left = self._own.get(name)
                    if left is not None and left.sent and left.sent[-1] is awaited:
                        left.sent.pop()
                        if not left.sent and left.queued is None:
                            del self._own[name]

    def set_many(self, values: Mapping[str, ParamValue], *, host: str | None = None) -> None:
        """Write each on the parameter server (ROS 1 has no multi-set); all checked first.

        The server holds every value for every node: ``host`` addresses nothing here.
        """
        for name, value in values.items():
            check_topic(name)
            check_param_value(value)
        for name, value in values.items():
            self.set(name, value)

    def flush(self, timeout_s: float = FLUSH_TIMEOUT_S) -> bool:
        """Wait until every queued write was handed to the master; False after ``timeout_s``."""
        return self._sender.flush(timeout_s)

    @property
    def alive(self) -> bool:
        """False once the push endpoint's or the sender's thread died."""
        return self._thread.alive and self._sender.alive

    def get(self, name: str) -> ParamValue:
        """The mirrored value of ``name`` (no call to the master)."""
        with self._lock:
            return self._mirror.get(name)

    def snapshot(self, prefix: str = "/") -> dict[str, ParamValue]:
        """The master's values under ``prefix``, with this process's writes not sent yet.

        The unsent ones are taken first: one sent meanwhile is in what the master returns.
        """
        unsent = self._sender.pending()
        out: dict[str, ParamValue] = {}
        namespace = prefix.rstrip("/") or "/"
        _flatten(namespace, self._master.call("getParam", namespace, missing_ok=True), out)
        for name, value in unsent:
            if not _under(name, namespace):
                continue
            if value is None:
                out.pop(name, None)
            else:
                out[name] = value
        return out

    def watch(self, callback: Callable[[str, ParamValue], None]) -> Handle:
        """Call ``callback(name, value)`` on every push (``None`` when deleted)."""
        return self._watchers.add(callback)

    def _stop_server(self) -> None:
        self._subscriber.close()
        self._server.shutdown()
        self._server.server_close()
        self._thread.join(CALL_TIMEOUT_S)

    def close(self) -> None:
        """Send the queued writes (bounded), unsubscribe from the master, stop the endpoint."""
        if not self._sender.close(FLUSH_TIMEOUT_S):
            log.warning("closing with parameter writes unsent after %.1f s", FLUSH_TIMEOUT_S)
        try:
            self._subscriber.call("unsubscribeParam", self._api, "/")
        except TransportError as err:
            log.debug("unsubscribeParam: %s", err)
        self._stop_server()


def _split(ros_topic: str) -> tuple[str, Variant]:
    if ros_topic.endswith(_OPTIMIZED) and len(ros_topic) > len(_OPTIMIZED):
        return ros_topic[: -len(_OPTIMIZED)], Variant.OPTIMIZED
    return ros_topic, Variant.FULL


class _Ros1Graph:
    """The master's view of who publishes and subscribes what, by the host of each node.

    A watched graph is re-read every ``poll_s`` by a ``PeriodicWorker``: a read that fails is
    logged and the next one retries; should the thread die all the same, ``alive`` says so.
    What is remembered of nodes (their URIs, when they last answered) is kept for the nodes of
    the last read only, so it never outgrows the graph.
    """

    def __init__(self, master: MasterClient, poll_s: float) -> None:
        self._master = master
        self._lock = threading.Lock()
        self._entries: frozenset[GraphEntry] | None = None
        self._uris: dict[str, str] = {}
        self._alive: dict[str, float] = {}
        self._watchers: CallbackList[[]] = CallbackList()
        self._worker = PeriodicWorker(
            self._poll, interval_s=poll_s, name="dbml-ros1-graph", log=log
        )
        self._polling = False
        self._reading = threading.Lock()
        """One read at a time (the poller's, a caller's): they share what is known of nodes."""

    def announce(self, role: Role, topic: str, variant: Variant) -> Handle:
        """Nothing to do: declaring the ROS publisher or subscriber registered it already."""
        check_topic(topic)
        return Closer(lambda: None)

    def _host(self, node: str) -> str | None:
        """The host part of a node's URI, if the node answers (cached for ``LIVENESS_S``)."""
        uri = self._uris.get(node)
        if uri is None:
            uri = self._master.call("lookupNode", node, missing_ok=True)
            if uri is None:
                return None
            self._uris[node] = uri
        now = time.monotonic()
        if now - self._alive.get(node, -LIVENESS_S) >= LIVENESS_S:
            try:
                with MasterClient(
                    uri, caller_id=self._master.caller_id, timeout_s=NODE_PING_TIMEOUT_S
                ) as node_api:
                    node_api.call("getPid")
            except TransportError:
                self._uris.pop(node, None)
                return None
            self._alive[node] = now
        return urlparse(uri).hostname

    def _read(self) -> frozenset[GraphEntry]:
        with self._reading:
            return self._read_locked()

    def _read_locked(self) -> frozenset[GraphEntry]:
        publishers, subscribers, _services = self._master.call("getSystemState")
        entries = set()
        listed: set[str] = set()
        for role, listing in ((Role.PUBLISHER, publishers), (Role.SUBSCRIBER, subscribers)):
            for ros_topic, nodes in listing:
                topic, variant = _split(ros_topic)
                for node in nodes:
                    listed.add(node)
                    host = self._host(node)
                    if host is not None:
                        entries.add(GraphEntry(role, host, topic, variant, f"{node} {ros_topic}"))
        for known in (self._uris, self._alive):  # forget the nodes that left the graph
            for node in [n for n in known if n not in listed]:
                known.pop(node, None)
        return frozenset(entries)

    def refresh(self) -> bool:
        """Re-read the graph; True if it changed."""
        fresh = self._read()
        with self._lock:
            changed = fresh != self._entries
            self._entries = fresh
        return changed

    def entries(self) -> frozenset[GraphEntry]:
        """The graph as last read (read now when nobody watches it)."""
        with self._lock:
            cached, polling = self._entries, self._polling
        if cached is None or not polling:
            self.refresh()  # nobody keeps it fresh: read it now
            with self._lock:
                cached = self._entries
        assert cached is not None
        return cached

    def watch(self, callback: Callable[[], None]) -> Handle:
        """Call ``callback()`` when the graph changes; the first watch starts the polling."""
        handle = self._watchers.add(callback)
        with self._lock:
            start, self._polling = not self._polling, True
        if start:
            self._worker.start()
        return handle

    def _poll(self) -> None:
        """One poll: re-read, and tell the watchers if the graph changed."""
        try:
            changed = self.refresh()
        except TransportError as err:  # the master is away: the next poll retries
            log.warning("graph: %s", err)
            return
        if changed:
            self._watchers.fire()

    @property
    def alive(self) -> bool:
        """False once the polling thread died."""
        return self._worker.alive

    def close(self) -> None:
        """Stop the polling (waiting for a poll in progress, bounded)."""
        self._worker.stop(timeout_s=CALL_TIMEOUT_S * 2)


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
        self._params = _Ros1Params(
            self._master, self.node_name, self._host, rosgraph.network.get_bind_address()
        )
        self._graph = _Ros1Graph(self._master, poll_s)
        # A node that exits without closing (a rospy user's) still sends its queued writes.
        atexit.register(self._flush_at_exit)

    def _flush_at_exit(self) -> None:
        if not self._closed and not self._params.flush(FLUSH_TIMEOUT_S):
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
    def params(self) -> _Ros1Params:
        """The parameter server, mirrored here."""
        return self._params

    def confirm_param(self, name: str, *, timeout_s: float) -> bool:
        """Whether the master holds what this process holds of ``name``, once it is sent.

        ``set`` only queues the write: a process that writes and exits must wait for it.
        """
        if not self._params.flush(timeout_s):
            return False
        try:
            held = self._master.call("getParam", name, missing_ok=True)
        except TransportError as err:
            log.warning("confirming %s: %s", name, err)
            return False
        return bool(held == self._params.get(name))

    @property
    def graph(self) -> _Ros1Graph:
        """The master's registrations, by host."""
        return self._graph

    def use_message_class(self, topic: str, data_class: type) -> None:
        """Carry ``topic`` (both copies) as ``data_class``, e.g. ``sensor_msgs.msg.Image``."""
        check_topic(topic)
        if not hasattr(data_class, "_md5sum") or not hasattr(data_class, "_type"):
            raise TransportError(f"data_class={data_class!r} is not a rospy message class")
        self._classes[topic] = data_class

    def camera_frame(self, topic: str, size_bytes: int) -> bytes:
        """A serialised ``sensor_msgs/Image`` of exactly ``size_bytes``, ``topic`` typed so.

        One mono8 row after the header: the size the optimizer sees is the size asked for.
        """
        from sensor_msgs.msg import Image

        self.use_message_class(topic, Image)
        image = Image(height=1, encoding="mono8", data=b"")
        pixels = size_bytes - len(serialize(image))
        image.width = image.step = pixels
        image.data = bytes(pixels)
        serialized = serialize(image)
        if len(serialized) != size_bytes:
            raise TransportError(f"size_bytes={size_bytes!r} is smaller than an empty Image")
        return serialized

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

        Its Python class is used when installed; else the md5 and definition come from the
        connection header of the first message received on ``topic``.
        """
        base, _variant = _split(check_topic(topic))
        package, _, name = msg_type.rpartition("/")
        package = package.removesuffix("/msg")  # ROS 2 spelling: pkg/msg/Name
        if not package or "/" in package or not name:
            raise TransportError(f"type={msg_type!r} must look like 'sensor_msgs/Image'")
        self._declared_types[base] = f"{package}/{name}"

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
