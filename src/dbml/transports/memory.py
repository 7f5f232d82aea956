"""The in-process transport: deterministic, synchronous, with an injectable clock.

Every ``MemoryTransport`` attached to one ``MemoryNetwork`` sees the others' messages,
parameters and graph, as separate hosts on one network would. Delivery is synchronous (a ``put``
returns after every callback ran), which makes unit tests exact. It is the runtime's test double
and runs the teleoperation demo in one process.

Each transport's parameters are a ``Replica`` of its own, as every other transport's are: the
network hands a write to every other replica before ``set`` returns, ordered by one counter of
the network's, and keeps every write for the transports that join later (as a parameter server
would).
"""

from __future__ import annotations

import itertools
import logging
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

from dbml.core.errors import TransportError
from dbml.protocol.schema import ParamValue
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
    of_topic,
    resolve_host,
)
from dbml.transports.callbacks import CallbackList
from dbml.transports.replica import Entry, Replica, Write

__all__ = ["ManualClock", "MemoryNetwork", "MemoryTransport"]

log = logging.getLogger("dbml.memory")


class ManualClock:
    """A clock that moves only when told to: ``clock.advance(0.5)``."""

    def __init__(self, start_s: float = 0.0) -> None:
        self._now = start_s

    def __call__(self) -> float:
        """The current time in seconds."""
        return self._now

    def advance(self, seconds: float) -> None:
        """Move the clock forward by ``seconds`` (never back)."""
        if seconds < 0:
            raise ValueError(f"seconds={seconds!r} must be >= 0")
        self._now += seconds


@dataclass
class MemoryNetwork:
    """The shared medium of memory transports: routes, parameter replicas and graph tokens."""

    routes: dict[str, CallbackList[[Sample]]] = field(default_factory=dict)
    tokens: dict[str, GraphEntry] = field(default_factory=dict)
    graph_watchers: CallbackList[[]] = field(default_factory=CallbackList)
    lock: threading.RLock = field(default_factory=threading.RLock)
    _replicas: list[Replica] = field(default_factory=list)
    _kept: dict[str, Entry] = field(default_factory=dict)
    """The newest write of every name, for a replica that joins later."""
    _ids: itertools.count[int] = field(default_factory=itertools.count)
    _stamps: itertools.count[int] = field(default_factory=lambda: itertools.count(1))

    def next_id(self) -> int:
        """A number no other declaration on this network has had."""
        return next(self._ids)

    def next_stamp(self) -> int:
        """The order of a parameter write on this network."""
        return next(self._stamps)

    def route(self, key: str) -> CallbackList[[Sample]]:
        """The subscribers of one topic variant (created empty on first use)."""
        with self.lock:
            return self.routes.setdefault(key, CallbackList())

    def join(self, writer: str) -> Replica:
        """A replica of this network's parameters, holding every write made so far."""
        replica = Replica(
            writer, send=self._deliver, log=log, clock_ns=self.next_stamp, threaded=False
        )
        with self.lock:
            kept = list(self._kept.items())
            self._replicas.append(replica)
        for name, held in kept:
            replica.merge(name, held.value, stamp=held.stamp, writer=held.writer)
        return replica

    def leave(self, replica: Replica) -> None:
        """``replica`` hears nothing more (its transport closed)."""
        with self.lock:
            if replica in self._replicas:
                self._replicas.remove(replica)

    def forge(self, values: Mapping[str, ParamValue], *, writer: str = "forger") -> None:
        """``values`` written by a peer that skipped ``set``'s checks, as any peer may.

        Every replica takes them as a write from the network (newest by the network's order):
        what the runtime does with a bad value from the network is tested with it.
        """
        self._deliver(Write(dict(values), self.next_stamp(), writer, batch=True))

    def _deliver(self, write: Write) -> None:
        """A replica's write, handed to every other one at once (outside the network's lock)."""
        with self.lock:
            for name, value in write.values.items():
                held = self._kept.get(name)
                if held is None or (held.stamp, held.writer) < (write.stamp, write.writer):
                    self._kept[name] = Entry(value, write.stamp, write.writer)
            others = [r for r in self._replicas if r.writer != write.writer]
        for replica in others:
            for name, value in write.values.items():
                replica.merge(name, value, stamp=write.stamp, writer=write.writer)


class _MemoryPublisher:
    def __init__(self, transport: MemoryTransport, topic: str, variant: Variant) -> None:
        self.topic = topic
        self._route = transport.network.route(variant.key(topic))
        self._transport = transport

    def put(self, payload: bytes, *, attachment: bytes | None = None) -> None:
        self._transport._check_open()
        self._route.fire(Sample(self.topic, bytes(payload), attachment))

    @property
    def has_subscribers(self) -> bool:
        return bool(self._route)

    def close(self) -> None:
        pass


class _MemoryGraph:
    def __init__(self, transport: MemoryTransport) -> None:
        self._transport = transport

    def announce(self, role: Role, topic: str, variant: Variant) -> Handle:
        check_topic(topic)
        transport = self._transport
        network = transport.network
        uid = f"{transport.host}.{network.next_id()}"
        entry = GraphEntry(role, transport.host, topic, variant, uid)
        with network.lock:
            network.tokens[uid] = entry
        transport._tokens.add(uid)
        network.graph_watchers.fire()

        def withdraw() -> None:
            with network.lock:
                network.tokens.pop(uid, None)
            transport._tokens.discard(uid)
            network.graph_watchers.fire()

        return Closer(withdraw)

    def entries(self, *, topic: str | None = None) -> frozenset[GraphEntry]:
        with self._transport.network.lock:
            return of_topic(frozenset(self._transport.network.tokens.values()), topic)

    def watch(self, callback: Callable[[], None], *, topic: str | None = None) -> Handle:
        """Every change calls every watcher: a test double's graph is small."""
        return self._transport.network.graph_watchers.add(callback)


class MemoryTransport(TransportBase):
    """One process's view of a ``MemoryNetwork`` (a fresh private network if none is given)."""

    delivers_at_once = True
    """Delivery is a call: nothing is ever queued on the way."""

    def __init__(
        self,
        network: MemoryNetwork | None = None,
        *,
        host: str | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.network = network if network is not None else MemoryNetwork()
        self.host = resolve_host(host)
        self.params = self.network.join(f"{self.host}.{self.network.next_id()}")
        self.graph = _MemoryGraph(self)
        self._clock = clock
        self._handles: set[Handle] = set()
        self._tokens: set[str] = set()
        self._closed = False

    def _check_open(self) -> None:
        if self._closed:
            raise TransportError(f"memory transport of host {self.host!r} is closed")

    def now(self) -> float:
        """The injected clock's seconds (``time.monotonic`` by default)."""
        return self._clock()

    def declare_publisher(
        self,
        topic: str,
        variant: Variant = Variant.FULL,
        *,
        priority: TransportPriority | None = None,
        express: bool = False,
    ) -> _MemoryPublisher:
        """A publisher whose ``put`` returns after every subscriber's callback ran.

        Delivery is synchronous, so there is no queue for ``priority`` or ``express`` to skip.
        """
        self._check_open()
        return _MemoryPublisher(self, check_topic(topic), variant)

    def subscribe(
        self, topic: str, callback: Callable[[Sample], None], variant: Variant = Variant.FULL
    ) -> Handle:
        """Call ``callback`` on the publishing thread for every message of ``topic``."""
        self._check_open()
        route = self.network.route(variant.key(check_topic(topic))).add(callback)

        def unsubscribe() -> None:
            route.close()
            self._handles.discard(handle)  # a closed subscription is not kept until exit

        handle = Closer(unsubscribe)
        self._handles.add(handle)
        return handle

    def close(self) -> None:
        """Undeclare everything this transport declared, as a process exit would."""
        if self._closed:
            return
        self._closed = True
        self.network.leave(self.params)
        for handle in list(self._handles):
            handle.close()
        with self.network.lock:
            for uid in self._tokens:
                self.network.tokens.pop(uid, None)
        if self._tokens:
            self._tokens.clear()
            self.network.graph_watchers.fire()
