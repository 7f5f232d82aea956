"""The in-process transport: deterministic, synchronous, with an injectable clock.

Every ``MemoryTransport`` attached to one ``MemoryNetwork`` sees the others' messages,
parameters and graph, as separate hosts on one network would. Delivery is synchronous (a ``put``
returns after every callback ran), which makes unit tests exact. It is the runtime's test double
and runs the teleoperation demo in one process.
"""

from __future__ import annotations

import itertools
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from dbml.core.errors import TransportError
from dbml.transports.base import (
    Closer,
    GraphEntry,
    Handle,
    ParamValue,
    Role,
    Sample,
    Variant,
    check_param_value,
    check_topic,
    resolve_host,
)

__all__ = ["ManualClock", "MemoryNetwork", "MemoryTransport"]


class ManualClock:
    """A clock that moves only when told to: ``clock.advance(0.5)``."""

    def __init__(self, start_s: float = 0.0) -> None:
        self._now = start_s

    def __call__(self) -> float:
        return self._now

    def advance(self, seconds: float) -> None:
        if seconds < 0:
            raise ValueError(f"seconds={seconds!r} must be >= 0")
        self._now += seconds


@dataclass(eq=False)
class _Callback:
    fn: Callable[..., None]
    closed: bool = False


@dataclass
class MemoryNetwork:
    """The shared medium of memory transports: routes, parameters and graph tokens."""

    routes: dict[str, list[_Callback]] = field(default_factory=dict)
    params: dict[str, tuple[ParamValue, int]] = field(default_factory=dict)
    param_watchers: list[_Callback] = field(default_factory=list)
    tokens: dict[str, GraphEntry] = field(default_factory=dict)
    graph_watchers: list[_Callback] = field(default_factory=list)
    lock: threading.RLock = field(default_factory=threading.RLock)
    _ids: itertools.count[int] = field(default_factory=itertools.count)
    _stamps: itertools.count[int] = field(default_factory=lambda: itertools.count(1))

    def next_id(self) -> int:
        return next(self._ids)

    def next_stamp(self) -> int:
        return next(self._stamps)

    def fire(self, callbacks: list[_Callback], *args: object) -> None:
        with self.lock:
            live = [c for c in callbacks if not c.closed]
        for callback in live:
            if not callback.closed:
                callback.fn(*args)


def _register(network: MemoryNetwork, where: list[_Callback], fn: Callable[..., None]) -> Handle:
    callback = _Callback(fn)
    with network.lock:
        where.append(callback)

    def remove() -> None:
        callback.closed = True
        with network.lock:
            if callback in where:
                where.remove(callback)

    return Closer(remove)


class _MemoryPublisher:
    def __init__(self, transport: MemoryTransport, topic: str, variant: Variant) -> None:
        self.topic = topic
        self._key = variant.key(topic)
        self._transport = transport

    def put(self, payload: bytes, attachment: bytes | None = None) -> None:
        self._transport._check_open()
        network = self._transport.network
        network.fire(
            network.routes.get(self._key, []), Sample(self.topic, bytes(payload), attachment)
        )

    @property
    def has_subscribers(self) -> bool:
        with self._transport.network.lock:
            return any(not c.closed for c in self._transport.network.routes.get(self._key, []))

    def close(self) -> None:
        pass


class _MemoryParams:
    def __init__(self, transport: MemoryTransport) -> None:
        self._transport = transport

    def set(self, name: str, value: ParamValue) -> None:
        check_param_value(value)
        network = self._transport.network
        with network.lock:
            network.params[name] = (value, network.next_stamp())
        network.fire(network.param_watchers, name, value)

    def get(self, name: str) -> ParamValue:
        with self._transport.network.lock:
            value, _ = self._transport.network.params.get(name, (None, 0))
        return value

    def snapshot(self, prefix: str = "/") -> dict[str, ParamValue]:
        with self._transport.network.lock:
            return {
                name: value
                for name, (value, _) in self._transport.network.params.items()
                if name.startswith(prefix) and value is not None
            }

    def watch(self, callback: Callable[[str, ParamValue], None]) -> Handle:
        return _register(self._transport.network, self._transport.network.param_watchers, callback)


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
        network.fire(network.graph_watchers)

        def withdraw() -> None:
            with network.lock:
                network.tokens.pop(uid, None)
            transport._tokens.discard(uid)
            network.fire(network.graph_watchers)

        return Closer(withdraw)

    def entries(self) -> frozenset[GraphEntry]:
        with self._transport.network.lock:
            return frozenset(self._transport.network.tokens.values())

    def watch(self, callback: Callable[[], None]) -> Handle:
        return _register(self._transport.network, self._transport.network.graph_watchers, callback)


class MemoryTransport:
    """One process's view of a ``MemoryNetwork`` (a fresh private network if none is given)."""

    def __init__(
        self,
        network: MemoryNetwork | None = None,
        *,
        host: str | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.network = network if network is not None else MemoryNetwork()
        self.host = resolve_host(host)
        self.params = _MemoryParams(self)
        self.graph = _MemoryGraph(self)
        self._clock = clock
        self._handles: list[Handle] = []
        self._tokens: set[str] = set()
        self._closed = False

    def _check_open(self) -> None:
        if self._closed:
            raise TransportError(f"memory transport of host {self.host!r} is closed")

    def now(self) -> float:
        return self._clock()

    def wait_for_peers(self, timeout_s: float) -> bool:
        """Nothing to wait for: the store is complete at once."""
        return True

    def confirm_param(self, name: str, *, timeout_s: float) -> bool:
        """Nothing to confirm: a write is everyone's at once."""
        return True

    def __enter__(self) -> MemoryTransport:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    def camera_frame(self, topic: str, size_bytes: int) -> bytes:
        """A synthetic camera frame of ``size_bytes``: raw bytes over this transport."""
        return bytes(size_bytes)

    def declare_publisher(self, topic: str, variant: Variant = Variant.FULL) -> _MemoryPublisher:
        self._check_open()
        return _MemoryPublisher(self, check_topic(topic), variant)

    def subscribe(
        self, topic: str, callback: Callable[[Sample], None], variant: Variant = Variant.FULL
    ) -> Handle:
        self._check_open()
        key = variant.key(check_topic(topic))
        with self.network.lock:
            route = self.network.routes.setdefault(key, [])
        handle = _register(self.network, route, callback)
        self._handles.append(handle)
        return handle

    def close(self) -> None:
        """Undeclare everything this transport declared, as a process exit would."""
        if self._closed:
            return
        self._closed = True
        for handle in self._handles:
            handle.close()
        with self.network.lock:
            for uid in self._tokens:
                self.network.tokens.pop(uid, None)
        if self._tokens:
            self._tokens.clear()
            self.network.fire(self.network.graph_watchers)
